"""`vlactl sweep` (paper Fig. 2): how much does adding alpha * d at one layer change the predicted actions?

For each layer, one at a time, and each alpha, alpha * d is added to that layer's read-out tokens at every forward
(`hooks.intervene`), over N frames spread evenly over a dataset; the first predicted action of each chunk is compared
with the unperturbed prediction under the same flow-matching noise (the policy is reset before every prediction).
d is the unit probe direction of a feature at that layer, all-ones / sqrt(d), or a random unit vector. The pooled
representation's L2 norm per layer is recorded too, so alpha can be read against the scale of each layer.

Writes `sweep.parquet` (layer, alpha, frame, change of each action dimension) and `norms.parquet` (layer, frame,
norm) under the run folder.
"""

from __future__ import annotations

import hashlib
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from omegaconf import DictConfig, OmegaConf

from vlactl.config import REPO_ROOT, resolve_path, save_config, stage_output
from vlactl.env.features import ACTION_FEATURES
from vlactl.errors import UsageError, check_choice, check_positive
from vlactl.io import atomic_write_parquet, ensure_writable_dir
from vlactl.models.base import POOLINGS, PolicyInput
from vlactl.models.hooks import capture, intervene
from vlactl.steering.collect import choose_layers, frame_batch
from vlactl.steering.offline import policy_and_frames, predict_chunk, run_batches
from vlactl.steering.probe_file import load_probe
from vlactl.steering.train_probes import METRICS_NAME, probe_filename

DIRECTIONS = ("probe", "ones", "random")
SWEEP_NAME, NORMS_NAME = "sweep.parquet", "norms.parquet"


def _check(cfg: DictConfig) -> None:
    if OmegaConf.is_missing(cfg, "model"):
        raise UsageError("which model? pass model=<registry name or checkpoint folder>, e.g. model=hybrid")
    check_choice("direction", cfg.direction, DIRECTIONS)
    check_choice("pooling", cfg.pooling, POOLINGS)
    for key in ("frames", "batch_size", "threads"):
        check_positive(key, cfg[key])
    if not cfg.alphas:
        raise UsageError("alphas must be a non-empty list of numbers, e.g. alphas=[-4,4]")
    if cfg.direction == "probe":
        if cfg.probes is None:
            raise UsageError("direction=probe needs probes=<probe run folder from `vlactl train-probes`>")
        stage_output(cfg.probes, METRICS_NAME, "probe run", "vlactl train-probes")


def directions(cfg: DictConfig, vla, layers: list[str]) -> dict[str, torch.Tensor]:
    """A unit vector per layer."""
    out = {}
    generator = torch.Generator().manual_seed(cfg.seed)
    for name in layers:
        width = vla.layer_width(name)
        if cfg.direction == "probe":
            path = resolve_path(cfg.probes) / "probes" / probe_filename(name, cfg.feature)
            if not path.is_file():
                raise UsageError(f"no {cfg.feature!r} probe for layer {name} in {cfg.probes!r} ({path.name} missing)")
            d = load_probe(path, model=vla.name, width=width, pooling=cfg.pooling).weight
        elif cfg.direction == "ones":
            d = torch.ones(width, dtype=torch.float64)
        else:
            d = torch.randn(width, generator=generator, dtype=torch.float64)
        out[name] = (d / d.norm()).float()
    return out


def _predict(vla, obs: PolicyInput, layer: str | None = None, u: torch.Tensor | None = None) -> np.ndarray:
    """First action of each predicted chunk, [B, 7], optionally with u added at `layer`."""
    hooks = None if layer is None else intervene(vla, [layer], lambda _, x: u.to(x.dtype).expand_as(x))
    return predict_chunk(vla, obs, hooks)[:, 0]


def default_output(cfg: DictConfig) -> Path:
    """outputs/sweeps/<model>_<feature, or the direction kind>."""
    name = cfg.feature if cfg.direction == "probe" else cfg.direction
    return REPO_ROOT / "outputs" / "sweeps" / f"{Path(str(cfg.model)).name}_{name}"


def run_sweep(cfg: DictConfig, load_policy=None) -> Path:
    """Sweep (or resume sweeping) and return the run folder: each batch of frames is a part, written once all its
    layers and alphas are done, which a re-run of the same command skips."""
    _check(cfg)
    vla, frames, rows, key = policy_and_frames(cfg, load_policy)
    layers = choose_layers(vla, cfg.layers)
    units = directions(cfg, vla, layers)
    out = resolve_path(cfg.output_dir) if cfg.output_dir else default_output(cfg)
    ensure_writable_dir(out, cfg.output_dir)
    key |= {"directions": hashlib.sha256(b"".join(units[name].numpy().tobytes() for name in layers)).hexdigest(),
            "layers": layers, "alphas": list(cfg.alphas), "pooling": cfg.pooling}
    tables = run_batches(
        out, key, (SWEEP_NAME, NORMS_NAME), rows, cfg.batch_size, desc=f"sweep {vla.name}",
        per_frame=len(layers) * len(cfg.alphas),
        work=lambda index, bar: _sweep_batch(vla, frame_batch(frames, index), index, layers, units, cfg, bar))
    order = {name: i for i, name in enumerate(layers)}
    for table, name in zip(tables, (SWEEP_NAME, NORMS_NAME)):
        table.insert(1, "layer_index", table["layer"].map(order))
        atomic_write_parquet(out / name, table)
    save_config(cfg, out)
    print(f"wrote {out / SWEEP_NAME} ({len(tables[0])} rows) and {out / NORMS_NAME}", file=sys.stderr)
    return out


def _sweep_batch(vla, obs: PolicyInput, index, layers, units, cfg, bar) -> tuple[pd.DataFrame, pd.DataFrame]:
    """One batch of frames: the change of every action dimension per layer and alpha, and each layer's norm."""
    with capture(vla, layers, cfg.pooling) as seen, torch.inference_mode():
        vla.encode_for(obs, cfg.pooling)
    norms = [pd.DataFrame({"layer": layer, "frame": index,
                           "norm": torch.stack(seen[layer]).mean(0).float().norm(dim=-1).numpy()})
             for layer in layers if seen[layer]]
    plain = _predict(vla, obs)
    changes = []
    for layer in layers:
        for alpha in cfg.alphas:
            delta = _predict(vla, obs, layer, float(alpha) * units[layer]) - plain
            table = pd.DataFrame(delta, columns=[f"d_{a}" for a in ACTION_FEATURES])
            table.insert(0, "frame", index)
            table.insert(0, "alpha", float(alpha))
            table.insert(0, "layer", layer)
            changes.append(table)
            bar.update(len(index))
    norms = pd.concat(norms, ignore_index=True) if norms else pd.DataFrame(columns=["layer", "frame", "norm"])
    return pd.concat(changes, ignore_index=True), norms
