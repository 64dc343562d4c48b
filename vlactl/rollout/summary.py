"""Success per task and overall, with counts, a 95% interval and mean episode length, from a rollout's episode
table."""

from __future__ import annotations

from pathlib import Path

import pandas as pd


def success_interval(successes: int, episodes: int) -> tuple[float, float] | None:
    """95% Wilson interval of a success rate: with 20 episodes, 16 successes are anything from 58% to 92%."""
    from scipy.stats import binomtest  # here: half a second of import that a rollout's start-up need not pay

    if not episodes:
        return None
    ci = binomtest(successes, episodes).proportion_ci(confidence_level=0.95, method="wilson")
    return float(ci.low), float(ci.high)


def _stats(episodes: pd.DataFrame) -> dict:
    n, ok = len(episodes), int(episodes["success"].sum())
    won = episodes.loc[episodes["success"].astype(bool), "steps"]
    out = {
        "episodes": n,
        "successes": ok,
        "success_rate": ok / n if n else None,
        "success_ci95": success_interval(ok, n),
        "mean_steps": float(episodes["steps"].mean()) if n else None,
        "mean_steps_success": float(won.mean()) if len(won) else None,
    }
    for column in episodes.columns:  # several constraints: satisfaction_<feature> too, each in its own window
        if column.startswith("satisfaction") and episodes[column].notna().any():
            out[column] = float(episodes[column].mean())  # mean over episodes of the window fraction
    return out


def summarise(episodes: pd.DataFrame) -> dict:
    per_task = {
        int(task): {"instruction": group["instruction"].iloc[0], **_stats(group)}
        for task, group in episodes.groupby("task_id", sort=True)
    }
    return {**_stats(episodes), "per_task": per_task}


def summarise_file(path: Path) -> dict:
    return summarise(pd.read_parquet(path))


def format_summary(summary: dict) -> str:
    def rate(s, interval=False):  # the interval overall; per task (10 episodes or so) it would span most of [0, 1]
        if s["success_rate"] is None:
            return "n/a"
        low, high = s["success_ci95"]
        return f"{100 * s['success_rate']:.0f}%" + (f", 95% CI {100 * low:.0f}–{100 * high:.0f}%" if interval else "")

    lines = [f"success {summary['successes']}/{summary['episodes']} ({rate(summary, interval=True)})"]
    if "satisfaction" in summary:
        each = ", ".join(f"{name} {100 * entry['satisfaction']:.0f}%" for name, entry in
                         summary.get("constraints", {}).items() if entry.get("satisfaction") is not None)
        lines.append(f"constraint {summary.get('constraint')} ({summary.get('method')}): satisfied on "
                     f"{100 * summary['satisfaction']:.0f}% of window steps" + (f" ({each})" if each else ""))
    for task, s in summary["per_task"].items():
        lines.append(f"  task {task}: {s['successes']}/{s['episodes']} ({rate(s)})  {s['instruction']}")
    return "\n".join(lines)
