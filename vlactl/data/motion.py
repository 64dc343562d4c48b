"""Two numbers of a demonstration set that constraints are stated in: the median speed of the hand (the speed
constraint's threshold, SPEC.md §3) and the metres the hand moves per unit of a steady translation command per step
(what the height barrier and the speed bound convert with; robosuite's OSC does not reach the commanded 5 cm per unit
in one 20 Hz step). A probe run records both (`provenance.json`), so a rollout can use them where the demonstrations are not
on disk, as on a fresh clone. Both read only LIBERO's 8-D state (position first) and the action, which every LIBERO
dataset has."""

from __future__ import annotations

from pathlib import Path

import numpy as np


STEADY_STEPS = 4  # a command is steady when the previous ones were within STEADY_CHANGE of it
STEADY_CHANGE = 0.05
MOVING = 0.5  # command units: steps commanding at least this much motion


def _steps(root: Path, steady: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Each step's displacement [n, 3] and translation command [n, 3], within episodes; with `steady`, only steps
    whose command has not changed for STEADY_STEPS steps (the hand has caught up with it)."""
    from vlactl.data.frames import read_columns
    from vlactl.data.lerobot_format import ACTION_KEY, STATE_KEY

    cols = read_columns(Path(root), [STATE_KEY, ACTION_KEY, "episode_index"])
    pos, act, ep = cols[STATE_KEY][:, :3], cols[ACTION_KEY][:, :3], cols["episode_index"]
    lag = STEADY_STEPS if steady else 0
    i = np.arange(lag, len(pos) - 1)
    keep = ep[i + 1] == ep[i - lag]  # a step, the next frame and the steps before it, all of one episode
    for j in range(1, lag + 1):
        keep &= np.linalg.norm(act[i - j] - act[i], axis=1) < STEADY_CHANGE
    return (pos[i + 1] - pos[i])[keep], act[i][keep]


def speed_median(root: Path) -> float:
    from vlactl.env.features import CONTROL_DT

    moved, _ = _steps(root)
    return float(np.median(np.linalg.norm(moved, axis=1)) / CONTROL_DT)


def metres_per_unit(root: Path) -> float:
    """The median distance moved per unit of command over the steps of a steady command of at least MOVING units:
    what a bound on the command holds the hand to once it has caught up. (The least-squares slope over every step,
    transients included, said 0.0101 m on the perturbed set where this says 0.0127, and a speed bound converted with
    it let the hand settle at 0.239 m/s against a 0.194 m/s threshold.)"""
    moved, command = _steps(root, steady=True)
    norm = np.linalg.norm(command, axis=1)
    fast = norm >= MOVING
    if not fast.any():  # a set without steady motion (a tiny or synthetic one): the slope over every step
        moved, command = _steps(root)
        return float((moved * command).sum() / (command * command).sum())
    return float(np.median(np.linalg.norm(moved[fast], axis=1) / norm[fast]))
