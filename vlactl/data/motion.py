"""Two numbers of a demonstration set that constraints are stated in: the median speed of the hand (the speed
constraint's threshold, SPEC.md §3) and the metres the hand moves per unit of translation command per step (what the
height barrier and the speed bound convert with; robosuite's OSC does not reach the commanded 5 cm per unit in one
20 Hz step). A probe run records both (`provenance.json`), so a rollout can use them where the demonstrations are not
on disk, as on a fresh clone. Both read only LIBERO's 8-D state (position first) and the action, which every LIBERO
dataset has."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def _steps(root: Path) -> tuple[np.ndarray, np.ndarray]:
    """Each step's displacement [n, 3] and translation command [n, 3], within episodes."""
    from vlactl.data.frames import read_columns
    from vlactl.data.lerobot_format import ACTION_KEY, STATE_KEY

    cols = read_columns(Path(root), [STATE_KEY, ACTION_KEY, "episode_index"])
    pos, act, ep = cols[STATE_KEY][:, :3], cols[ACTION_KEY][:, :3], cols["episode_index"]
    same = ep[1:] == ep[:-1]  # a step and the next frame of its own episode
    return (pos[1:] - pos[:-1])[same], act[:-1][same]


def speed_median(root: Path) -> float:
    from vlactl.env.features import CONTROL_DT

    moved, _ = _steps(root)
    return float(np.median(np.linalg.norm(moved, axis=1)) / CONTROL_DT)


def metres_per_unit(root: Path) -> float:
    """The least-squares slope of each step's displacement on its command, over x, y and z together."""
    moved, command = _steps(root)
    return float((moved * command).sum() / (command * command).sum())
