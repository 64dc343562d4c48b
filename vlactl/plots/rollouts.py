"""`vlactl plot rollouts`: the paper's Figs. 4-8 from constrained rollout runs.

- `violins_<feature>`: per condition (constraint value) and method, the distribution over window steps of the
  constrained quantity relative to its reference level (gripper action vs 0, z vs the start height, speed vs the
  threshold): the constraint asks for the side of 0 the condition names (Figs. 4, 5, 7).
- `success_vs_satisfaction`: per condition and method, mean constraint satisfaction against success rate over tasks,
  with a one-standard-deviation ellipse of the per-task values (Figs. 6, 8);
- `summary.md`: success (with its 95% Wilson interval) and satisfaction per constraint and method, the unconstrained
  run included.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.patches import Ellipse
from omegaconf import DictConfig

from vlactl.config import resolve_path
from vlactl.errors import UsageError
from vlactl.io import atomic_write_text
from vlactl.plots.files import check_formats, plt, save_figure
from vlactl.rollout.summary import success_interval

METHOD_ORDER = ("none", "prompt", "control", "alpha")


def load_runs(folders: list[Path]) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Episodes and in-window steps of constrained runs, each row tagged with feature, condition and method."""
    episodes, steps = [], []
    for folder in folders:
        ep = pd.read_parquet(folder / "episodes.parquet")
        if ep.empty or (ep["constraint"] == "none").all():
            continue
        st = pd.read_parquet(folder / "steps.parquet")
        st = st[st["in_window"].astype(bool)].merge(ep[["task_id", "episode", "constraint", "method"]])
        episodes.append(ep)
        steps.append(st)
    if not episodes:
        raise UsageError(f"no constrained rollout runs among {[str(f) for f in folders]}; run "
                         "`vlactl rollout --constraint ... --method ...` first")
    out = []
    for table in (pd.concat(episodes, ignore_index=True), pd.concat(steps, ignore_index=True)):
        split = table["constraint"].str.split("=", expand=True)
        out.append(table.assign(feature=split[0], condition=split[1]))
    return out[0], out[1]


def _methods(table: pd.DataFrame) -> list[str]:
    return sorted(table["method"].unique(), key=lambda m: METHOD_ORDER.index(m) if m in METHOD_ORDER else 99)


def figure_violins(steps: pd.DataFrame, feature: str):
    rows = steps[steps["feature"] == feature]
    conditions, methods = sorted(rows["condition"].unique()), _methods(rows)
    fig, axes = plt.subplots(1, len(conditions), figsize=(3.2 * len(conditions), 3.4), squeeze=False,
                             constrained_layout=True)
    for ax, condition in zip(axes[0], conditions):
        data = [(rows[(rows["condition"] == condition) & (rows["method"] == m)]) for m in methods]
        values = [(d["constraint_value"] - d["constraint_level"]).to_numpy() for d in data]
        shown = [i for i, v in enumerate(values) if len(v)]
        ax.violinplot([values[i] for i in shown], positions=shown, showmedians=True)
        ax.axhline(0, color="0.5", lw=0.8, ls="--")
        ax.set_xticks(range(len(methods)), methods)
        ax.set_title(f"{feature}={condition}")
    axes[0][0].set_ylabel(f"{feature} in the window − reference")
    return fig


def figure_success_vs_satisfaction(episodes: pd.DataFrame):
    fig, ax = plt.subplots(figsize=(5, 4), constrained_layout=True)
    groups = episodes.groupby(["feature", "condition", "method"])
    colours = {m: f"C{i}" for i, m in enumerate(_methods(episodes))}
    markers = dict(zip(sorted(episodes["constraint"].unique()), "osD^v<>p*h"))
    for (feature, condition, method), group in groups:
        per_task = group.groupby("task_id").agg(sat=("satisfaction", "mean"), ok=("success", "mean"))
        x, y = per_task["sat"].mean(), per_task["ok"].mean()
        colour = colours[method]
        ax.scatter(x, y, color=colour, marker=markers[f"{feature}={condition}"], zorder=3)
        ax.add_patch(Ellipse((x, y), 2 * np.nan_to_num(per_task["sat"].std()), 2 * np.nan_to_num(per_task["ok"].std()),
                             color=colour, alpha=0.15, lw=0))
    for method, colour in colours.items():
        ax.scatter([], [], color=colour, label=method)
    for name, marker in markers.items():
        ax.scatter([], [], color="0.3", marker=marker, label=name)
    ax.set_xlabel("constraint satisfaction")
    ax.set_ylabel("task success rate")
    ax.set_xlim(-0.05, 1.05)
    ax.set_ylim(-0.05, 1.05)
    ax.legend(fontsize=7, loc="lower left")
    return fig


def summary_table(folders: list[Path]) -> str:
    """Markdown: success and satisfaction per constraint and method, over every run (the unconstrained one too)."""
    episodes = pd.concat([pd.read_parquet(f / "episodes.parquet") for f in folders], ignore_index=True)
    if "satisfaction" not in episodes:
        episodes["satisfaction"] = np.nan
    rows = ["| constraint | method | episodes | success (95% CI) | satisfaction |", "|---|---|---|---|---|"]
    for (constraint, method), group in episodes.groupby(["constraint", "method"], sort=True):
        sat = group["satisfaction"].mean()
        low, high = success_interval(int(group["success"].sum()), len(group))
        rows.append(f"| {constraint} | {method} | {len(group)} | {100 * group['success'].mean():.0f}% "
                    f"({100 * low:.0f}–{100 * high:.0f}%) | {'–' if np.isnan(sat) else f'{100 * sat:.0f}%'} |")
    return "\n".join(rows) + "\n"


def run_plot_rollouts(cfg: DictConfig) -> list[Path]:
    check_formats(cfg.formats)
    root = resolve_path(cfg.root)
    folders = [resolve_path(r) for r in cfg.runs] if cfg.runs else sorted(p.parent for p in root.glob("*/episodes.parquet"))
    missing = [str(f) for f in folders if not (f / "episodes.parquet").is_file()]
    if missing:
        raise UsageError(f"{missing[0]!r} is not a rollout run folder (no episodes.parquet)")
    episodes, steps = load_runs(folders)
    out = resolve_path(cfg.output_dir) if cfg.output_dir else root / "figures"
    written = []
    for feature in sorted(steps["feature"].unique()):
        written += save_figure(figure_violins(steps, feature), out, f"violins_{feature}", cfg.formats, cfg.dpi)
    written += save_figure(figure_success_vs_satisfaction(episodes), out, "success_vs_satisfaction", cfg.formats,
                           cfg.dpi)
    atomic_write_text(out / "summary.md", summary_table(folders))
    written.append(out / "summary.md")
    print(f"wrote {len(written)} files under {out}", file=sys.stderr)
    return written
