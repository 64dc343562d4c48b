"""Quantile normalisation (as π0.5 and OpenVLA do): the 1st..99th percentile of each dimension maps to [-1, 1]."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

MIN_RANGE = 1e-3  # a dimension that barely moves (e.g. roll commands) is scaled as if it spanned this much


@dataclass(frozen=True)
class Normalizer:
    low: torch.Tensor
    high: torch.Tensor

    @classmethod
    def fit(cls, x: np.ndarray) -> "Normalizer":
        low, high = np.quantile(np.asarray(x, dtype=np.float64), [0.01, 0.99], axis=0)
        return cls(torch.as_tensor(low, dtype=torch.float32), torch.as_tensor(high, dtype=torch.float32))

    def _scale(self) -> torch.Tensor:
        return ((self.high - self.low) / 2).clamp(min=MIN_RANGE)

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        return (x - (self.high + self.low) / 2) / self._scale()

    def inverse(self, x: torch.Tensor) -> torch.Tensor:
        return x * self._scale() + (self.high + self.low) / 2

    def to_dict(self) -> dict:
        return {"low": self.low.tolist(), "high": self.high.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "Normalizer":
        return cls(torch.tensor(d["low"], dtype=torch.float32), torch.tensor(d["high"], dtype=torch.float32))


def save_stats(path: Path, stats: dict[str, Normalizer]) -> None:
    from vlactl.io import atomic_write_json

    atomic_write_json(path, {key: norm.to_dict() for key, norm in stats.items()})


def load_stats(path: Path) -> dict[str, Normalizer]:
    return {key: Normalizer.from_dict(d) for key, d in json.loads(Path(path).read_text()).items()}
