"""A probe as one safetensors file: the raw-space weight and bias (plus the standardisation that was folded into
them), with metadata naming the model, layer, read-out pooling, feature and kind, and its test metrics."""

from __future__ import annotations

import json
from pathlib import Path

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, safe_open, save_file

from vlactl.errors import UsageError
from vlactl.io import atomic_path
from vlactl.steering.probes import Probe

FORMAT, VERSION = "vlactl.probe", "1"


def save_probe(probe: Probe, path: Path) -> None:
    tensors = {
        "weight": probe.weight.double().contiguous(),
        "bias": torch.tensor([probe.bias], dtype=torch.float64),
        "mean": probe.mean.double().contiguous(),
        "std": probe.std.double().contiguous(),
    }
    meta = {
        "format": FORMAT, "version": VERSION, "feature": probe.feature, "kind": probe.kind, "layer": probe.layer,
        "model": probe.model, "pooling": probe.pooling, "width": str(probe.width), "positive": probe.positive,
        "space": "raw: reading = weight . x + bias on the unstandardised pooled representation",
        "metrics": json.dumps(probe.metrics),
    }
    with atomic_path(Path(path)) as tmp:
        save_file(tensors, str(tmp), metadata=meta)


def load_probe(path: Path, *, model: str | None = None, width: int | None = None, pooling: str | None = None) -> Probe:
    """Read a probe; with model / width / pooling given, refuse one trained for something else (UsageError)."""
    path = Path(path)
    if not path.is_file():
        raise UsageError(f"no probe file {str(path)!r}; train probes with `vlactl train-probes`")
    try:
        with safe_open(str(path), framework="pt") as fh:
            meta = fh.metadata() or {}
        tensors = load_file(str(path))
    except (SafetensorError, OSError) as exc:
        raise UsageError(f"{str(path)!r} is not a readable safetensors file ({exc})") from None
    if meta.get("format") != FORMAT:
        raise UsageError(f"{str(path)!r} is not a vlactl probe (format {meta.get('format')!r})")
    probe = Probe(
        feature=meta["feature"], kind=meta["kind"], layer=meta["layer"], model=meta["model"], pooling=meta["pooling"],
        weight=tensors["weight"], bias=float(tensors["bias"][0]), mean=tensors["mean"], std=tensors["std"],
        positive=meta.get("positive", ""), metrics=json.loads(meta.get("metrics", "{}")),
    )
    probe.check_fits(model, width, pooling)
    return probe
