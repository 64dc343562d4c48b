"""`vlactl plot rollouts`: the paper's Figs. 4-8 from constrained rollout runs.

- `violins_<feature>`: one violin pair per method, the two conditions side by side (open | closed, low | high), of
  the constrained quantity over window steps, normalised as the paper does: the gripper's closure (0 open .. 1
  closed, from the measured aperture), the height and the speed minus their reference (start height, threshold);
  means and medians marked (Figs. 4, 5, 7).
- `success_vs_satisfaction`: one panel per constraint (rows: feature; columns: condition), mean satisfaction against
  success rate per method with a one-standard-deviation ellipse over tasks; hollow markers of decreasing size, so a
  method on top of another stays visible (Figs. 6, 8);
- `summary.md`: success (with its 95% Wilson interval) and satisfaction per constraint and method, the unconstrained
  run included; runs with other seeds pooled, each set's successes listed, and the success against the unconstrained
  episodes that start the same way (a perturbed run a row of its own, against the unperturbed episodes).

A run under several constraints (`height=high,speed=low`) is drawn in the panel of each of its constraints, judged by
that constraint alone (its `_<feature>` columns), as the method `control [height=high,speed=low]`; summary.md gives
its combined satisfaction and each constraint's.
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
from vlactl.io import atomic_write_text, concat_tables
from vlactl.plots.files import check_formats, plt, save_figure
from vlactl.rollout.summary import success_interval

METHOD_ORDER = ("none", "prompt", "control", "control+pause", "alpha", "meandiff", "filter", "filter+pause")
MARKERS = "osD^vP*X"
YLABEL = {"gripper": "gripper closure (0 open, 1 closed)", "height": "z − start height (m)",
          "speed": "speed − threshold (m/s)"}


def load_runs(folders: list[Path]) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Episodes and in-window steps of constrained runs, each row tagged with feature, condition and method; a run
    under several constraints once per constraint (`per_constraint`)."""
    episodes, steps = [], []
    for folder in folders:
        ep = pd.read_parquet(folder / "episodes.parquet")
        if ep.empty or (ep["constraint"] == "none").all():
            continue
        for ep, st in per_constraint(ep, pd.read_parquet(folder / "steps.parquet")):
            episodes.append(ep)
            steps.append(st[st["in_window"].astype(bool)].merge(ep[["task_id", "episode", "constraint", "method"]]))
    if not episodes:
        raise UsageError(f"no constrained rollout runs among {[str(f) for f in folders]}; run "
                         "`vlactl rollout --constraint ... --method ...` first")
    out = []
    for table in (concat_tables(episodes), concat_tables(steps)):
        split = table["constraint"].str.split("=", expand=True)
        out.append(table.assign(feature=split[0], condition=split[1]))
    return out[0], out[1]


def per_constraint(episodes: pd.DataFrame, steps: pd.DataFrame) -> list[tuple[pd.DataFrame, pd.DataFrame]]:
    """A run's tables as [(episodes, steps)]: as they are for one constraint; for several, one pair per constraint,
    its own columns (`satisfaction_<feature>`, `in_window_<feature>`, ...) under the single-constraint names and the
    method labelled with the run's full constraint, `control [height=high,speed=low]`."""
    full = str(episodes["constraint"].iloc[0])
    if "," not in full:
        return [(episodes, steps)]
    out = []
    for name in full.split(","):
        feature = name.partition("=")[0]
        judged = {f"{column}_{feature}": column for column in ("in_window", "constraint_value", "constraint_level",
                                                                "satisfied")}
        out.append((episodes.assign(constraint=name, satisfaction=episodes[f"satisfaction_{feature}"],
                                    method=episodes["method"] + f" [{full}]"),
                    steps.drop(columns=[c for c in judged.values() if c in steps]).rename(columns=judged)))
    return out


def _methods(table: pd.DataFrame) -> list[str]:
    def order(label: str):
        method = label.split(" [")[0]  # several constraints: `control [height=high,speed=low]`
        return METHOD_ORDER.index(method) if method in METHOD_ORDER else 99, label

    return sorted(table["method"].unique(), key=order)


def normalised(steps: pd.DataFrame, feature: str) -> np.ndarray:
    """The quantity Figs. 4, 5, 7 draw: the gripper's closure from its aperture, else value minus reference."""
    if feature == "gripper":
        return 1.0 - steps["gripper"].to_numpy(dtype=float)
    return (steps["constraint_value"] - steps["constraint_level"]).to_numpy(dtype=float)


def figure_violins(steps: pd.DataFrame, feature: str):
    rows = steps[steps["feature"] == feature]
    conditions, methods = sorted(rows["condition"].unique()), _methods(rows)
    fig, ax = plt.subplots(figsize=(1.3 + 1.2 * len(methods), 3.4), constrained_layout=True)
    width = 0.8 / len(conditions)
    for c, condition in enumerate(conditions):
        offset = (c - (len(conditions) - 1) / 2) * width
        values = {i: normalised(rows[(rows["condition"] == condition) & (rows["method"] == m)], feature)
                  for i, m in enumerate(methods)}
        shown = [i for i, v in values.items() if len(v)]
        if not shown:
            continue
        parts = ax.violinplot([values[i] for i in shown], positions=[i + offset for i in shown], widths=width * 0.9,
                              showmeans=True, showmedians=True)
        for body in parts["bodies"]:
            body.set_facecolor(f"C{c}")
            body.set_alpha(0.45)
        parts["cmedians"].set_color("k")
        parts["cmeans"].set_color(f"C{c}")
        parts["cmeans"].set_linestyle(":")
        ax.scatter([], [], color=f"C{c}", marker="s", label=f"{feature}={condition}")
    if feature != "gripper":
        ax.axhline(0, color="0.5", lw=0.8, ls="--")
    ax.set_xticks(range(len(methods)), [m.replace(" [", "\n[") for m in methods], fontsize=7)
    ax.set_ylabel(YLABEL.get(feature, feature))
    ax.set_title(f"{feature} in the window (median —, mean ···)", fontsize=9)
    ax.legend(fontsize=7)
    return fig


def figure_success_vs_satisfaction(episodes: pd.DataFrame):
    features = sorted(episodes["feature"].unique())
    columns = max(episodes.groupby("feature")["condition"].nunique())
    fig, axes = plt.subplots(len(features), columns, figsize=(3.4 * columns, 3.0 * len(features)), squeeze=False,
                             constrained_layout=True)
    methods = _methods(episodes)
    style = {m: (f"C{i}", MARKERS[i % len(MARKERS)], 110 - 12 * i) for i, m in enumerate(methods)}
    for r, feature in enumerate(features):
        conditions = sorted(episodes.loc[episodes["feature"] == feature, "condition"].unique())
        for c in range(columns):
            ax = axes[r][c]
            if c >= len(conditions):
                ax.axis("off")
                continue
            rows = episodes[(episodes["feature"] == feature) & (episodes["condition"] == conditions[c])]
            for method in methods:
                group = rows[rows["method"] == method]
                if group.empty:
                    continue
                per_task = group.groupby("task_id").agg(sat=("satisfaction", "mean"), ok=("success", "mean"))
                x, y = per_task["sat"].mean(), per_task["ok"].mean()
                colour, marker, size = style[method]
                # the outline keeps an ellipse of zero width (every task equally satisfied) visible as a bar
                ax.add_patch(Ellipse((x, y), 2 * np.nan_to_num(per_task["sat"].std()),
                                     2 * np.nan_to_num(per_task["ok"].std()), facecolor=colour, edgecolor=colour,
                                     alpha=0.15, lw=1.2))
                ax.scatter(x, y, s=size, marker=marker, facecolors="none", edgecolors=colour, linewidths=1.6,
                           zorder=3, label=method)
            ax.set_title(f"{feature}={conditions[c]}", fontsize=9)
            ax.set_xlim(-0.05, 1.05)
            ax.set_ylim(-0.05, 1.05)
            ax.set_xlabel("constraint satisfaction")
            ax.set_ylabel("task success rate")
    # one legend under the panels: inside a panel it can hide a method's point
    drawn = {label: handle for ax in axes.flat for handle, label in zip(*ax.get_legend_handles_labels())}
    shown = [m for m in methods if m in drawn]
    fig.legend([drawn[m] for m in shown], shown, loc="outside lower center", ncols=min(len(shown), 6), fontsize=8)
    return fig


def summary_table(folders: list[Path]) -> str:
    """Markdown: success and satisfaction per constraint and method, over every run (the unconstrained one too).
    Runs of one constraint and method with other seeds pool into one row, each set's successes listed (a set: the
    episodes of one run's `seed=`); `× unconstrained` compares with the unconstrained episodes among the runs that
    start the same way (model, task, episode, set), where every episode of the row has its unconstrained twin."""
    episodes = pd.concat([pd.read_parquet(f / "episodes.parquet") for f in folders], ignore_index=True)
    if "satisfaction" not in episodes:
        episodes["satisfaction"] = np.nan
    episodes["set"] = episodes["seed"] - episodes["episode"] if "seed" in episodes else 0
    plain = (episodes["constraint"] == "none") & (episodes["method"] == "none")
    if "perturbation" in episodes:  # a perturbed run is its own row, never an unconstrained twin
        taken = episodes["perturbation"] != "none"
        plain &= ~taken
        episodes.loc[taken, "method"] += ", perturb=" + episodes.loc[taken, "perturbation"]
    keys = ["task_id", "episode", "set"]
    if "model" in episodes:  # twins of the same model; with several models, each its own rows
        keys.append("model")
        if episodes["model"].nunique() > 1:
            episodes["method"] = episodes["model"] + ": " + episodes["method"]
    free = episodes[plain].drop_duplicates(keys).set_index(keys)["success"]
    rows = ["| constraint | method | episodes | success (95% CI) | per set | × unconstrained | satisfaction |",
            "|---|---|---|---|---|---|---|"]
    for (constraint, method), group in episodes.groupby(["constraint", "method"], sort=True):
        sat = group["satisfaction"].mean()
        low, high = success_interval(int(group["success"].sum()), len(group))
        names = constraint.split(",") if "," in constraint else []  # several: each constraint's own too
        each = [f"{name} {100 * group['satisfaction_' + name.partition('=')[0]].mean():.0f}%" for name in names]
        shown = "–" if np.isnan(sat) else f"{100 * sat:.0f}%" + (f" ({', '.join(each)})" if each else "")
        sets = group.groupby("set")["success"].agg(["sum", "size"])
        per_set = ", ".join(f"{k}: {int(r['sum'])}/{int(r['size'])}" for k, r in sets.iterrows())
        per_set = per_set if len(sets) > 1 else "–"
        against = "–" if plain[group.index].all() else _against(group, free, keys)  # the twins themselves: no ratio
        rows.append(f"| {constraint} | {method} | {len(group)} | {100 * group['success'].mean():.0f}% "
                    f"({100 * low:.0f}–{100 * high:.0f}%) | {per_set} | {against} | {shown} |")
    return "\n".join(rows) + "\n"


def _against(group: pd.DataFrame, free: pd.Series, keys: list[str]) -> str:
    """`0.969 × (341/352)`: the row's successes over those of its unconstrained twins, or – where some have none."""
    twins = free.reindex(pd.MultiIndex.from_frame(group[keys]))
    if twins.isna().any() or not twins.sum():
        return "–"
    successes, base = int(group["success"].sum()), int(twins.sum())
    return f"{successes / base:.3f} × ({successes}/{base})"


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
