"""Hybrid processing: actions are normalised floats, the flow-matching targets."""

from __future__ import annotations

import torch

from vlactl.models.parts.processing import Processor


class HybridProcessor(Processor):
    def actions(self, actions: torch.Tensor) -> torch.Tensor:
        return self.stats["action"](torch.as_tensor(actions, dtype=torch.float32))
