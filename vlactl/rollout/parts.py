"""Per-episode results on disk: workers write one part per finished episode, the run merges them into two tables.

A part is `parts/taskTT/epKKKK.parquet` (its steps) and then `epKKKK.json` (its episode row); both are written
atomically and the row last, so a row on disk means the episode is complete. That is what an interrupted run
resumes from, and the merged tables never hold a half-finished episode.
"""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd

from vlactl.env.features import ACTION_FEATURES, STATE_FEATURES, speeds
from vlactl.io import atomic_write_json, atomic_write_parquet, concat_tables

EPISODE_KEY = ["task_id", "episode"]
EPISODE_COLUMNS = [
    "suite", *EPISODE_KEY, "instruction", "init_state", "seed", "success", "steps", "wall_s", "model",
    "method", "constraint", "start_gripper",  # the gripper state the episode settled in (open, or closed)
    "satisfaction",  # the fraction of the constraint window's steps satisfied (several: of the steps in any window,
                     # every constraint covering the step satisfied; then also satisfaction_<feature> per constraint)
    "perturbation",  # vlactl.env.perturbations.Perturbation.name, or none
]
# With a constraint, steps also get the columns of vlactl.rollout.constraints.judge_all and of
# vlactl.rollout.constrained.reading_columns.
OBJECT_COLUMNS = ["object_x", "object_y", "object_z"]  # the object the task moves (Observation.object_pos)
STEP_COLUMNS = [*EPISODE_KEY, "t", *STATE_FEATURES, *ACTION_FEATURES, "speed", *OBJECT_COLUMNS]


def stem(out: Path, task: int, episode: int) -> Path:
    return Path(out) / "parts" / f"task{task:02d}" / f"ep{episode:04d}"


def is_done(out: Path, task: int, episode: int) -> bool:
    return stem(out, task, episode).with_suffix(".json").exists()


def steps_frame(task: int, episode: int, result) -> pd.DataFrame:
    """One row per policy step t: the state before action t, action t, the speed it caused, and where the task's
    object was before action t."""
    n = result.steps
    frame = pd.DataFrame(result.states[:n], columns=list(STATE_FEATURES))
    frame[list(ACTION_FEATURES)] = result.actions
    frame["speed"] = speeds(result.states[:, :3])[:n]
    frame[OBJECT_COLUMNS] = result.object_positions[:n]
    frame.insert(0, "t", range(n))
    frame.insert(0, "episode", episode)
    frame.insert(0, "task_id", task)
    return frame[STEP_COLUMNS]


def write(out: Path, row: dict, steps: pd.DataFrame) -> None:
    base = stem(out, row["task_id"], row["episode"])
    atomic_write_parquet(base.with_suffix(".parquet"), steps)
    atomic_write_json(base.with_suffix(".json"), row)  # last: marks the episode done


def merge(out: Path, keys: list[tuple[int, int]]) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The episode and step tables of the finished episodes among `keys`, in key order."""
    done = [stem(out, t, k) for t, k in sorted(keys) if is_done(out, t, k)]
    rows = [json.loads(s.with_suffix(".json").read_text()) for s in done]
    own = dict.fromkeys(key for row in rows for key in row if key.startswith("satisfaction_"))  # several constraints
    episodes = pd.DataFrame(rows, columns=[*EPISODE_COLUMNS, *own])
    steps = concat_tables([pd.read_parquet(s.with_suffix(".parquet")) for s in done], STEP_COLUMNS)
    return episodes, steps
