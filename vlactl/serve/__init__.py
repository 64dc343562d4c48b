"""A policy server: one loaded model answering many rollout workers over a websocket (docs/scale-out.md)."""
