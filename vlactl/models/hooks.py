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


def masked_mean(hidden: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """[B, T, d] pooled over the True tokens of a bool [B, T] mask -> [B, d]."""
    m = mask.to(hidden.dtype)
    # a batched matrix product: no [B, T, d] temporary (the hooks run at every forward of every captured layer)
    return torch.bmm(m[:, None, :], hidden)[:, 0] / m.sum(1, keepdim=True).clamp(min=1)


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

    def make_hook(name):
        def hook(hidden):
            mask = vla.token_mask(name, pooling)
            if mask.any():
                readings[name].append(masked_mean(hidden.detach(), mask))

        return hook

    with _hooks(vla, layers, make_hook):
        yield readings


@contextmanager
def intervene(vla: VLA, layers: list[str], fn: Intervention, pooling: str = "prefix") -> Iterator[None]:
    """At each forward through a chosen layer, call fn(layer, pooled [B, d]) and add the returned u [B, d] to every
    token of the read-out set, so the pooled reading moves by exactly u. fn returns None to leave the layer alone;
    it is not called for forwards with an empty token set.
    """

    def make_hook(name):
        def hook(hidden):
            mask = vla.token_mask(name, pooling)
            if not mask.any():
                return None
            u = fn(name, masked_mean(hidden.detach(), mask))
            if u is None:
                return None
            return hidden + mask.to(hidden.dtype)[..., None] * u.to(hidden.dtype)[:, None, :]

        return hook

    with _hooks(vla, layers, make_hook):
        yield
