"""Closed-loop LIBERO evaluation (`vlactl rollout`): episodes in worker processes, per-episode parts, merged tables."""
