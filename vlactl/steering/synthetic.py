"""Synthetic activations with features planted linearly in chosen layers: the fixture for tests and benchmarks,
where the right answer is known (R^2 high where a feature is planted, about 0 elsewhere)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from vlactl.steering.activations import FEATURES as SPEC_FEATURES


@dataclass
class Planted:
    x: np.ndarray  # [L, N, d] float32 activations
    latent: np.ndarray  # [N, F] the smooth per-episode processes the features are made of
    episodes: np.ndarray  # [N]
    planted: np.ndarray  # [L, F] bool: feature f is linearly present in layer l


def planted_activations(
    n_layers: int = 6, n_episodes: int = 40, frames: int = 50, d: int = 32, n_features: int = 4,
    planted_every: int = 2, strength: float = 3.0, seed: int = 0,
) -> Planted:
    """Feature f is planted in layers l with (l + f) % planted_every == 0, along a random unit direction, on top of
    per-episode nuisance structure, a large per-layer offset (residual streams have one) and unit noise."""
    rng = np.random.default_rng(seed)
    n = n_episodes * frames
    latent = np.empty((n_episodes, frames, n_features))
    latent[:, 0] = rng.standard_normal((n_episodes, n_features))
    for t in range(1, frames):  # AR(1), phi = 0.95: consecutive frames of an episode are near-duplicates
        latent[:, t] = 0.95 * latent[:, t - 1] + np.sqrt(1 - 0.95**2) * rng.standard_normal((n_episodes, n_features))
    latent = latent.reshape(n, n_features)
    episodes = np.repeat(np.arange(n_episodes), frames)
    planted = (np.arange(n_layers)[:, None] + np.arange(n_features)[None, :]) % planted_every == 0
    x = np.empty((n_layers, n, d), dtype=np.float32)
    for layer in range(n_layers):
        dirs = rng.standard_normal((n_features, d))
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        signal = (latent * (strength * planted[layer])) @ dirs
        nuisance = rng.standard_normal((n_episodes, 4))[episodes] @ rng.standard_normal((4, d))
        offset = 10.0 * rng.standard_normal(d)
        x[layer] = signal + nuisance + offset + rng.standard_normal((n, d))
    return Planted(x=x, latent=latent, episodes=episodes, planted=planted)


def spec_labels(latent: np.ndarray, episodes: np.ndarray) -> pd.DataFrame:
    """A labels table in the activation store's schema (docs/formats.md) whose 15 SPEC features are affine in the
    latent columns, except the gripper aperture (a squashed latent, so 'closed' = aperture < 0.5 = latent < 0)."""
    if latent.shape[1] != len(SPEC_FEATURES):
        raise ValueError(f"need {len(SPEC_FEATURES)} latent columns, got {latent.shape[1]}")
    cols = dict(zip(SPEC_FEATURES, latent.T))
    frame_index = np.concatenate([np.arange(c) for c in np.unique(episodes, return_counts=True)[1]])
    df = pd.DataFrame({
        "episode": episodes.astype(np.int64),
        "frame_index": frame_index.astype(np.int64),
        "task_id": (episodes % 10).astype(np.int64),
        "init_state": (episodes // 10).astype(np.int64),
        "instruction": [f"task {e % 10}" for e in episodes],
    })
    for name, value in cols.items():
        df[name] = value * 0.1 + 0.5 if name in ("x", "y", "z") else value
    df["gripper"] = 1 / (1 + np.exp(-3 * cols["gripper"]))
    df["speed"] = cols["speed"] * 0.05 + 0.2
    return df
