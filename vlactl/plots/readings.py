"""`vlactl plot readings` (paper Fig. 3): one probe's readings at its layer over dataset frames under no
intervention, a fixed alpha W push, and the minimal controller, with the box drawn. The readings are those the
`Steerer` logs (before and after its intervention), also written to `readings.parquet` beside the figure."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from omegaconf import DictConfig, OmegaConf

from vlactl.config import resolve_path, stage_output
from vlactl.errors import UsageError
from vlactl.io import atomic_write_parquet
from vlactl.models.base import PolicyInput
from vlactl.plots.files import check_formats, plt, save_figure
from vlactl.steering.collect import frame_batch, model_frames, spread
from vlactl.steering.probe_file import load_probe
from vlactl.steering.steer import Constraint, Steerer
from vlactl.steering.train_probes import METRICS_NAME, best_layers, probe_filename

CONDITIONS = (("none", "no intervention"), ("alpha", "fixed αW"), ("control", "controller"))


def readings(vla, probe, zmin: float, zmax: float, alpha: float, obs: PolicyInput) -> pd.DataFrame:
    """Per condition and frame, the reading the layer holds after that condition's intervention (first forward)."""
    rows = []
    for method, _ in CONDITIONS:
        box = Constraint(probe, zmin, zmax) if method == "control" else Constraint(probe)
        steerer = Steerer(vla, [box], method="control" if method == "none" else method, alpha=alpha)
        vla.reset()
        with steerer, torch.inference_mode():
            vla.predict_action_chunk(obs)
        first = [row for row in steerer.log if row["forward"] == 0]
        key = "before" if method == "none" else "after"  # with an open box the controller does nothing: 'none'
        rows += [{"condition": method, "row": row["row"], "reading": row[key]} for row in first]
    return pd.DataFrame(rows)


def figure_readings(table: pd.DataFrame, zmin: float, zmax: float, title: str):
    fig, ax = plt.subplots(figsize=(5.5, 3.6), constrained_layout=True)
    for i, (method, label) in enumerate(CONDITIONS):
        values = table.loc[table["condition"] == method, "reading"].to_numpy()
        jitter = np.random.default_rng(i).uniform(-0.15, 0.15, len(values))
        ax.scatter(i + jitter, values, s=8, alpha=0.6, color=f"C{i}")
    for bound in (zmin, zmax):
        if math.isfinite(bound):
            ax.axhline(bound, color="k", ls="--", lw=1)
    ax.set_xticks(range(len(CONDITIONS)), [label for _, label in CONDITIONS])
    ax.set_ylabel("probe reading")
    ax.set_title(title, fontsize=9)
    return fig


def run_plot_readings(cfg: DictConfig, load_policy=None) -> list[Path]:
    from vlactl.models.registry import policy_loader

    check_formats(cfg.formats)
    if OmegaConf.is_missing(cfg, "model") or OmegaConf.is_missing(cfg, "probes"):
        raise UsageError("pass model=<name or checkpoint> and probes=<probe run folder from `vlactl train-probes`>")
    run = stage_output(cfg.probes, METRICS_NAME, "probe run", "vlactl train-probes")
    table = pd.read_parquet(run / METRICS_NAME)
    layer = cfg.layer or next(iter(best_layers(table[table["feature"] == cfg.feature], steerable=True)["layer"]), None)
    path = run / "probes" / probe_filename(str(layer), cfg.feature)
    if layer is None or not path.is_file():
        raise UsageError(f"no {cfg.feature!r} probe for layer {layer} in {cfg.probes!r}")
    torch.set_num_threads(cfg.threads)
    vla = (load_policy or policy_loader(cfg))(str(cfg.model))
    probe = load_probe(path, model=vla.name, width=vla.layer_width(layer))
    frames = model_frames(vla, resolve_path(cfg.dataset), resolve_path(cfg.cache_dir))
    index_all = spread(len(frames), cfg.frames)
    parts = []
    for start in range(0, len(index_all), cfg.batch_size):
        index = index_all[start : start + cfg.batch_size]
        obs = frame_batch(frames, index)
        parts.append(readings(vla, probe, float(cfg.zmin), float(cfg.zmax), float(cfg.alpha), obs).assign(
            frame=lambda d, index=index: index[d["row"]]))
    result = pd.concat(parts, ignore_index=True).drop(columns="row")
    out = resolve_path(cfg.output_dir) if cfg.output_dir else run / "figures"
    atomic_write_parquet(out / "readings.parquet", result.assign(layer=layer, feature=cfg.feature))
    controlled = result.loc[result["condition"] == "control", "reading"]
    inside = controlled.between(cfg.zmin - 1e-4, cfg.zmax + 1e-4).mean()  # 1e-4: float32 rounding of x + u
    title = f"{cfg.feature} @ {layer}: {100 * inside:.0f}% of controlled readings in [{cfg.zmin:g}, {cfg.zmax:g}]"
    written = save_figure(figure_readings(result, cfg.zmin, cfg.zmax, title), out, "fig3_readings", cfg.formats, cfg.dpi)
    print(f"{title}; wrote {len(written)} files under {out}", file=sys.stderr)
    return written
