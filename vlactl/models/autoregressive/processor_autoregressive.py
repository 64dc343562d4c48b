"""Autoregressive processing: normalised actions <-> bin ids (OpenVLA's discretisation), ends of [-1, 1] included."""

from __future__ import annotations

import torch

from vlactl.models.parts.processing import Processor


class AutoregressiveProcessor(Processor):
    def actions(self, actions: torch.Tensor) -> torch.Tensor:
        """Raw actions -> bin ids (long); values beyond the 1st..99th percentiles go to the end bins."""
        x = self.stats["action"](torch.as_tensor(actions, dtype=torch.float32)).clamp(-1, 1)
        return torch.round((x + 1) / 2 * (self.config.bins - 1)).long()

    def bin_centers(self, ids: torch.Tensor) -> torch.Tensor:
        """Bin ids -> normalised actions."""
        return ids.float() / (self.config.bins - 1) * 2 - 1
