"""`vlactl plot controllability`: a controllability run's layer x feature heatmap of gain, each cell annotated with
its R² (and, for binary features, the share of predictions that crossed to the asked side); a second run beside it.

Gains are in different units per feature (Δdz per unit of the z reading, Δgripper per logit), so each column's
colour is its gain divided by the largest |gain| of that feature over both panels: the panels compare cell by cell.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd
from omegaconf import DictConfig, OmegaConf

from vlactl.config import stage_output
from vlactl.plots.files import plotted_run, plt, save_figure
from vlactl.steering.controllability import CONTROLLABILITY_NAME


def _title(run: Path) -> str:
    """The run folder and the probe run it measured."""
    config = run / "config.yaml"
    probes = OmegaConf.load(config).get("probes") if config.is_file() else None
    return f"{run.name}\nprobes: {Path(str(probes)).name}" if probes else run.name


def figure_controllability(tables: list[tuple[str, pd.DataFrame]]):
    features = list(dict.fromkeys(f for _, table in tables for f in table["feature"]))
    scale = pd.concat([table for _, table in tables]).groupby("feature")["gain"].apply(lambda g: g.abs().max())
    height = max(len(table["layer"].unique()) for _, table in tables)
    fig, axes = plt.subplots(1, len(tables), figsize=(1.1 * len(features) * len(tables) + 2, 0.55 * height + 1.6),
                             constrained_layout=True, squeeze=False)
    for ax, (title, table) in zip(axes[0], tables):
        rows = table.drop_duplicates("layer").sort_values("layer_index")["layer"].tolist()
        cell = table.set_index(["layer", "feature"])
        grid = np.full((len(rows), len(features)), np.nan)
        for i, layer in enumerate(rows):
            for j, feature in enumerate(features):
                if (layer, feature) not in cell.index:
                    continue
                row = cell.loc[(layer, feature)]
                grid[i, j] = row["gain"] / scale[feature] if scale[feature] > 0 else 0.0
                note = f"{row['gain']:+.2g}\nR² {row['r2']:.2f}" if np.isfinite(row["r2"]) else f"{row['gain']:+.2g}"
                if np.isfinite(row["cross_share"]):
                    note += f"\n{row['cross_share']:.0%} cross"
                ax.text(j, i, note, ha="center", va="center", fontsize=6)
        image = ax.imshow(grid, cmap="coolwarm", vmin=-1, vmax=1, aspect="auto")
        ax.set_xticks(range(len(features)), features, rotation=45, ha="right", fontsize=7)
        ax.set_yticks(range(len(rows)), rows, fontsize=7)
        ax.set_title(title, fontsize=8)
    fig.colorbar(image, ax=axes[0].tolist(), label="gain / largest |gain| of the feature", shrink=0.8)
    return fig


def run_plot_controllability(cfg: DictConfig) -> list[Path]:
    stage = (CONTROLLABILITY_NAME, "controllability run", "vlactl controllability")
    runs = [plotted_run(cfg, *stage)] + ([] if cfg.compare is None else [stage_output(cfg.compare, *stage)])
    fig = figure_controllability([(_title(run), pd.read_parquet(run / CONTROLLABILITY_NAME)) for run in runs])
    written = save_figure(fig, runs[0] / "figures", "controllability", cfg.formats, cfg.dpi)
    print(f"wrote {len(written)} files under {runs[0] / 'figures'}", file=sys.stderr)
    return written
