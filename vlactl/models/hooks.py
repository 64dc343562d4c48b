"""Read and write a VLA's layer outputs through forward hooks, at a read-out token set (see vlactl.models.base).

Both context managers register one hook per chosen layer and remove them on exit, error or not. A hook does a
couple of tensor ops per forward (no loops over tokens), so capturing every layer costs little.
"""

from __future__ import annotations

from contextlib import contextmanager
from typing import Callable, Iterator

import torch

from vlactl.models.base import VLA

Intervention = Callable[[str, torch.Tensor], "torch.Tensor | None"]


def pool_weights(mask: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """Bool [B, T] -> [B, 1, T] weights of the mean over the True tokens (all zero where a row has none)."""
    m = mask.to(dtype)
    return (m / m.sum(1, keepdim=True).clamp(min=1))[:, None, :]


def masked_mean(hidden: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """[B, T, d] pooled over the True tokens of a bool [B, T] mask -> [B, d]."""
    # a batched matrix product: no [B, T, d] temporary
    return torch.bmm(pool_weights(mask, hidden.dtype), hidden)[:, 0]


class _Pooling:
    """masked_mean at a read-out set for hooks, None where the set is empty. A model sets one mask object per stack
    and forward, shared by the stack's layers, so the weights and the emptiness check are worked out once per
    forward rather than per layer: per-op dispatch is most of what a hook costs (and `any` syncs a GPU)."""

    def __init__(self, vla: VLA, pooling: str):
        self.vla, self.pooling = vla, pooling
        self._mask = self._weights = None
        self._any = False

    def __call__(self, name: str, hidden: torch.Tensor) -> torch.Tensor | None:
        mask = self.vla.token_mask(name, self.pooling)
        if mask is not self._mask or self._weights.dtype != hidden.dtype:
            self._mask, self._any, self._weights = mask, bool(mask.any()), pool_weights(mask, hidden.dtype)
        return torch.bmm(self._weights, hidden.detach())[:, 0] if self._any else None


@contextmanager
def _hooks(vla: VLA, layers: list[str], make_hook) -> Iterator[None]:
    handles = [handle for name in layers for handle in vla.hook_layer(name, make_hook(name))]
    try:
        yield
    finally:
        for handle in handles:
            handle.remove()


@contextmanager
def capture(vla: VLA, layers: list[str], pooling: str = "prefix") -> Iterator[dict[str, list[torch.Tensor]]]:
    """Yield {layer: [pooled [B, d] of each forward through it]}; forwards with an empty token set add nothing."""
    readings: dict[str, list[torch.Tensor]] = {name: [] for name in layers}
    pool = _Pooling(vla, pooling)

    def make_hook(name):
        def hook(hidden):
            pooled = pool(name, hidden)
            if pooled is not None:
                readings[name].append(pooled)

        return hook

    with _hooks(vla, layers, make_hook):
        yield readings


@contextmanager
def intervene(vla: VLA, layers: list[str], fn: Intervention, pooling: str = "prefix") -> Iterator[None]:
    """At each forward through a chosen layer, call fn(layer, pooled [B, d]) and add the returned u [B, d] to every
    token of the read-out set, so the pooled reading moves by exactly u. fn returns None to leave the layer alone;
    it is not called for forwards with an empty token set.
    """
    pool = _Pooling(vla, pooling)

    def make_hook(name):
        def hook(hidden):
            pooled = pool(name, hidden)
            u = None if pooled is None else fn(name, pooled)
            if u is None:
                return None
            mask = vla.token_mask(name, pooling)
            return hidden + mask.to(hidden.dtype)[..., None] * u.to(hidden.dtype)[:, None, :]

        return hook

    with _hooks(vla, layers, make_hook):
        yield
