"""`vlactl plot probes`: the paper's Fig. 1 and per-layer metric curves, from a probe run's metrics.parquet.

Fig. 1 shows, for each feature, the probe of its best layer (test R^2 for regression, balanced accuracy for binary
features) against the trivial baseline: MAE vs the training mean, accuracy vs the majority class. MAE is divided by
the baseline's MAE so that features in metres, radians and normalised actions share one axis (the baseline sits at 1).
"""

from __future__ import annotations

import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only; no display on these machines
import matplotlib.ticker  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

from vlactl.plots.files import plotted_run, save_figure  # noqa: E402
from vlactl.steering.probes import LOGISTIC, REGRESSION  # noqa: E402
from vlactl.steering.train_probes import METRICS_NAME, best_layers  # noqa: E402

PROBE, BASE = "#1f78b4", "#a6cee3"  # the paper's Paired palette: trained probe dark, baseline light
CURVES = [  # (column, label, baseline column or None, kind)
    ("r2", "test R$^2$", "baseline_r2", REGRESSION),
    ("mae", "test MAE", "baseline_mae", REGRESSION),
    ("cv_r2", "cross-validated R$^2$ (train episodes)", None, REGRESSION),
    ("accuracy", "test accuracy", "baseline_accuracy", LOGISTIC),
    ("balanced_accuracy", "test balanced accuracy", "baseline_balanced_accuracy", LOGISTIC),
]


def _bars(ax, labels, probe, base, ylabel, notes):
    pos = np.arange(len(labels))
    ax.bar(pos - 0.2, base, 0.4, color=BASE)
    ax.bar(pos + 0.2, probe, 0.4, color=PROBE)
    for p, value, note in zip(pos, probe, notes):
        inside = value >= 0.5  # a tall bar holds its layer's name; above it the name would reach the title
        ax.annotate(note, (p + 0.2, 0 if inside else value), textcoords="offset points", xytext=(0, 2), ha="center",
                    fontsize=6, rotation=90, va="bottom", color="white" if inside else "black")
    ax.set_xticks(pos, labels, rotation=45, ha="right")
    ax.set_ylabel(ylabel)
    ax.set_ylim(0, max(1.15, 1.05 * np.nanmax(np.r_[probe, base])))  # a probe worse than its baseline stays in view


def figure_best(table: pd.DataFrame):
    best = best_layers(table)
    reg, log = best[best["kind"] == REGRESSION], best[best["kind"] == LOGISTIC]
    panels = [p for p in (reg, log) if len(p)]
    fig, axes = plt.subplots(1, len(panels), figsize=(3 + 0.45 * len(reg) + 0.9 * len(log), 3.6),
                             gridspec_kw={"width_ratios": [max(len(p), 2) for p in panels]}, squeeze=False)
    axes = list(axes[0])
    if len(reg):
        ax = axes.pop(0)
        scale = reg["baseline_mae"].where(reg["baseline_mae"] > 0)
        _bars(ax, reg["feature"], reg["mae"] / scale, reg["baseline_mae"] / scale, "test MAE / baseline MAE",
              reg["layer"])
        ax.set_title("regression: MAE (lower is better)", fontsize=9)
    if len(log):
        ax = axes.pop(0)
        _bars(ax, log["feature"], log["accuracy"], log["baseline_accuracy"], "test accuracy", log["layer"])
        ax.set_title("binary: accuracy", fontsize=9)
    handles = [plt.Rectangle((0, 0), 1, 1, color=c) for c in (BASE, PROBE)]
    names = ["baseline: training mean / majority class", "probe at the best layer (named on the bar)"]
    fig.legend(handles, names, loc="upper center", bbox_to_anchor=(0.5, 0.93), ncol=2, fontsize=8, frameon=False)
    fig.suptitle(f"Linear observability per feature ({table['model'].iloc[0]}, {table['pooling'].iloc[0]} pooling)",
                 fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.88))
    return fig


def _grid(n: int):
    cols = min(4, n)
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.3 * rows), squeeze=False, sharex=True)
    for ax in axes.flat[n:]:
        ax.axis("off")
    return fig, axes.flat[:n], cols


def _layer_ticks(axes, cols: int, table: pd.DataFrame) -> None:
    """Layer names under the lowest panel of each column (sharex hides the others')."""
    names = table.drop_duplicates("layer_index").sort_values("layer_index")
    step = max(1, len(names) // 8)
    for i, ax in enumerate(axes):
        if i + cols >= len(axes):
            ax.set_xticks(names["layer_index"][::step], names["layer"][::step], rotation=60, fontsize=6)
            ax.xaxis.set_tick_params(labelbottom=True)


def _top_legend(fig, ax) -> None:
    """One legend above the panels, where it hides no curve."""
    handles, labels = ax.get_legend_handles_labels()
    rows = fig.axes[0].get_gridspec().nrows
    fig.legend(handles, labels, loc="upper center", ncol=min(len(labels), 6), fontsize=7, frameon=False)
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.25 / (2.3 * rows)))


def figure_curves(table: pd.DataFrame, column: str, label: str, baseline: str | None, kind: str):
    rows = table[table["kind"] == kind]
    features = list(dict.fromkeys(rows["feature"]))
    fig, axes, cols = _grid(len(features))
    for ax, feature in zip(axes, features):
        part = rows[rows["feature"] == feature].sort_values("layer_index")
        ax.plot(part["layer_index"], part[column], color=PROBE, marker=".", label="probe")
        if baseline is not None:
            ax.plot(part["layer_index"], part[baseline], color=BASE, ls="--", label="baseline")
        ax.set_title(feature, fontsize=9)
        ax.tick_params(labelsize=7)
    _layer_ticks(axes, cols, table)
    fig.supylabel(label, fontsize=9)
    _top_legend(fig, axes[0])
    return fig


def figure_robustness(table: pd.DataFrame):
    norms = sorted(float(c.removeprefix("robust_mean_")) for c in table.columns if c.startswith("robust_mean_"))
    features = list(dict.fromkeys(table["feature"]))
    fig, axes, cols = _grid(len(features))
    colours = plt.cm.viridis(np.linspace(0.15, 0.85, len(norms)))
    for ax, feature in zip(axes, features):
        part = table[table["feature"] == feature].sort_values("layer_index")
        for rho, colour in zip(norms, colours):
            ax.plot(part["layer_index"], part[f"robust_mean_{rho:g}"], color=colour, label=f"mean, {rho:g}||x||")
            ax.plot(part["layer_index"], part[f"robust_max_{rho:g}"], color=colour, ls=":", label=f"max, {rho:g}||x||")
        ax.set_yscale("log")
        ax.yaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))  # mathtext labels are slow
        ax.yaxis.set_minor_locator(matplotlib.ticker.NullLocator())  # hundreds of minor ticks: slow, no help
        unit = "probability" if part["kind"].iloc[0] == LOGISTIC else "feature units"
        ax.set_title(f"{feature} ({unit})", fontsize=9)
        ax.tick_params(labelsize=7)
    _layer_ticks(axes, cols, table)
    fig.supylabel("|f(x + eps) - f(x)|, random eps", fontsize=9)
    _top_legend(fig, axes[0])
    return fig


def run_plot_probes(cfg: DictConfig) -> list[Path]:
    run = plotted_run(cfg, METRICS_NAME, "probe run", "vlactl train-probes")
    table = pd.read_parquet(run / METRICS_NAME)
    out = run / "figures"
    written = save_figure(figure_best(table), out, "fig1_best_layer", cfg.formats, cfg.dpi)
    for column, label, baseline, kind in CURVES:
        if column in table and (table["kind"] == kind).any():
            written += save_figure(figure_curves(table, column, label, baseline, kind), out, f"layers_{column}",
                             cfg.formats, cfg.dpi)
    if any(c.startswith("robust_mean_") for c in table.columns):
        written += save_figure(figure_robustness(table), out, "layers_robustness", cfg.formats, cfg.dpi)
    print(f"wrote {len(written)} files under {out}", file=sys.stderr)
    return written
