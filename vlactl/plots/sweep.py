"""`vlactl plot sweep`: the paper's Fig. 2 from a sweep run's sweep.parquet and norms.parquet."""

from __future__ import annotations

import sys
from pathlib import Path

import pandas as pd
from omegaconf import DictConfig

from vlactl.plots.files import plotted_run, plt, save_figure
from vlactl.steering.sweep import NORMS_NAME, SWEEP_NAME

PANELS = [("d_dyaw", "mean change of predicted Δyaw"), ("d_gripper_action", "mean change of predicted gripper action")]


def figure_sweep(sweep: pd.DataFrame, norms: pd.DataFrame):
    layers = sweep.drop_duplicates("layer_index").sort_values("layer_index")
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6), constrained_layout=True)
    cmap = plt.get_cmap("coolwarm")
    alphas = sorted(sweep["alpha"].unique())
    for ax, (column, label) in zip(axes, PANELS):
        mean = sweep.groupby(["alpha", "layer_index"])[column].mean()
        for i, alpha in enumerate(alphas):
            curve = mean.loc[alpha]
            ax.plot(curve.index, curve.values, marker="o", ms=3, color=cmap(i / max(len(alphas) - 1, 1)),
                    label=f"α = {alpha:g}")
        ax.axhline(0, color="0.6", lw=0.8)
        ax.set_ylabel(label)
    norm = norms.groupby("layer_index")["norm"].mean()
    axes[2].plot(norm.index, norm.values, marker="o", ms=3, color="0.2")
    axes[2].set_ylabel("mean ‖x‖ (pooled)")
    for ax in axes:
        ax.set_xticks(layers["layer_index"], layers["layer"], rotation=60, fontsize=7)
        ax.set_xlabel("layer")
    axes[0].legend(fontsize=7, ncol=2)
    return fig


def run_plot_sweep(cfg: DictConfig) -> list[Path]:
    run = plotted_run(cfg, SWEEP_NAME, "sweep run", "vlactl sweep")
    fig = figure_sweep(pd.read_parquet(run / SWEEP_NAME), pd.read_parquet(run / NORMS_NAME))
    written = save_figure(fig, run / "figures", "fig2_sweep", cfg.formats, cfg.dpi)
    print(f"wrote {len(written)} files under {run / 'figures'}", file=sys.stderr)
    return written
