"""Train/test split and cross-validation folds by episode: frames of one episode are near-duplicates, so a frame-level
split would leak the test set into training and flatter every probe."""

from __future__ import annotations

import numpy as np


def split_by_episode(episodes: np.ndarray, test_fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Row indices (train, test); whole episodes go to one side, chosen by a seeded permutation of the episode ids."""
    ids, row_id = np.unique(episodes, return_inverse=True)
    if len(ids) < 2:
        raise ValueError(f"need at least 2 episodes to split by episode, got {len(ids)}")
    n_test = min(max(1, round(test_fraction * len(ids))), len(ids) - 1)
    is_test_id = np.zeros(len(ids), dtype=bool)
    is_test_id[np.random.default_rng(seed).permutation(len(ids))[:n_test]] = True
    is_test = is_test_id[row_id]
    return np.flatnonzero(~is_test), np.flatnonzero(is_test)


def episode_folds(episodes: np.ndarray, k: int, seed: int) -> np.ndarray:
    """Fold id in [0, k) per row: whole episodes per fold, folds of near-equal episode counts."""
    ids, row_id = np.unique(episodes, return_inverse=True)
    if len(ids) < k:
        raise ValueError(f"need at least {k} episodes for {k}-fold cross-validation, got {len(ids)}")
    fold_of_id = np.empty(len(ids), dtype=np.int64)
    # seed + 1: the folds' permutation is independent of the test split's
    fold_of_id[np.random.default_rng(seed + 1).permutation(len(ids))] = np.arange(len(ids)) % k
    return fold_of_id[row_id]
