"""Perturbations of the arm: something else takes over for a stretch of policy steps, then hands control back.

One definition serves both sides of the robustness question: `vlactl rollout perturb=...` measures how often a
policy still succeeds after it (docs/steering.md), and `vlactl demos perturbed_episodes_per_task=N` records the
expert finding its way back from it, labelled with the expert's own commands (DART-style), so a policy can learn that
way back. Each kind maps the policy's (or expert's) 7-D action and the current state to the executed action:

- `raise`: the hand is driven `size` metres (default 0.08) straight up from where the stretch began, then held there;
- `hold`: the hand is held where the stretch began;
- `shift`: the hand is driven `size` metres (default 0.05) sideways (world +y) and held there;
- `slow`: the commanded motion is scaled by `size` (default 1/3);
- `close`: the gripper is commanded closed, on nothing or whatever is there;
- `tilt`: the hand is held where the stretch began and turned `size` radians (default 0.07) about the world x axis,
  then held so: the few degrees a representation push leaves the hand turned by (docs/steering.md).
Positions and orientations are servoed with proportional laws on the delta-pose action; rotations are otherwise held
(zero command) while the arm is taken over. The gripper stays the policy's, except under `close`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from vlactl.errors import UsageError
from vlactl.expert.scripted import ROT_SCALE, ExpertConfig

# kind -> (default size, allowed (low, high], what the size means); None: the kind takes no size
KINDS = {
    "raise": (0.08, (0.0, 0.2), "metres up"),
    "hold": (None, None, ""),
    "shift": (0.05, (0.0, 0.2), "metres sideways"),
    "slow": (1 / 3, (0.0, 1.0), "speed factor"),
    "close": (None, None, ""),
    "tilt": (0.07, (0.0, 0.5), "radians about the world x axis"),
}
DEMONSTRATED = ("raise", "hold", "shift", "slow", "close")  # what perturbed demonstrations cycle through (tilt: its own kind)
TILT_SIZE = (0.03, 0.15)  # radians, either way: the turns tilted demonstrations draw from unless told otherwise
SERVO_GAIN = 14.0  # action units per metre of position error: ~70% of the error per step, as the scripted expert
ROTATION_GAIN = ExpertConfig.kr / ROT_SCALE  # action units per radian of orientation error: the expert's servo
CLOSE = 1.0


@dataclass(frozen=True)
class Perturbation:
    kind: str
    start: int = 0  # first perturbed policy step
    steps: int = 15  # how many steps it lasts
    size: float | None = None  # None: the kind's default

    @property
    def name(self) -> str:
        size = "" if self.size is None else f"{self.size:g}"
        return f"{self.kind}{size and ':' + size}@{self.start}+{self.steps}"

    def active(self, t: int) -> bool:
        return self.start <= t < self.start + self.steps

    def hook(self):
        """A step hook for `run_episode` (`hook(t, obs, action) -> action`), fresh per episode: it remembers where
        the hand was when the stretch began."""
        anchor = {}

        def perturb(t: int, obs, action: np.ndarray) -> np.ndarray:
            if not self.active(t):
                return action
            state = np.asarray(obs.state, dtype=np.float64)
            anchor.setdefault("start", state.copy())
            return self.apply(action, state, anchor["start"])

        return perturb

    def apply(self, action: np.ndarray, state: np.ndarray, start: np.ndarray) -> np.ndarray:
        """The executed action while the perturbation is on, given the robot state (x, y, z, roll, pitch, yaw, g) now
        and when it began."""
        out = np.array(action, dtype=np.float64)
        size = KINDS[self.kind][0] if self.size is None else self.size
        if self.kind == "slow":
            out[:6] *= size
        elif self.kind == "close":
            out[6] = CLOSE
        else:
            offset = {"raise": (0.0, 0.0, size), "shift": (0.0, size, 0.0)}.get(self.kind, (0.0, 0.0, 0.0))
            out[:3] = np.clip(SERVO_GAIN * (start[:3] + np.asarray(offset) - state[:3]), -1.0, 1.0)
            out[3:6] = 0.0
            if self.kind == "tilt":  # the orientation error in world axes, as the expert servoes it
                turned = Rotation.from_rotvec([size, 0.0, 0.0]) * Rotation.from_euler("xyz", start[3:6])
                error = (turned * Rotation.from_euler("xyz", state[3:6]).inv()).as_rotvec()
                out[3:6] = np.clip(ROTATION_GAIN * error, -1.0, 1.0)
        return out


def parse_perturbation(kind: str | None, start: int = 0, steps: int = 15, size: float | None = None,
                       max_steps: int | None = None) -> Perturbation | None:
    """`perturb=raise` (+ perturb_start, perturb_steps, perturb_size) -> Perturbation; `none` -> None. Out-of-range
    values are a one-line UsageError naming what is allowed."""
    if kind in (None, "", "none"):
        return None
    if kind not in KINDS:
        raise UsageError(f"unknown perturbation {kind!r}; allowed: none, {', '.join(KINDS)}")
    default, bounds, meaning = KINDS[kind]
    if size is not None:
        if bounds is None:
            raise UsageError(f"perturb={kind} takes no size, got perturb_size={size}")
        low, high = bounds
        if not low < float(size) <= high:
            raise UsageError(f"perturb_size={size} out of range for perturb={kind}: {meaning} in ({low:g}, {high:g}]")
        size = float(size)
    if int(start) < 0:
        raise UsageError(f"perturb_start must be >= 0, got {start}")
    limit = max_steps if max_steps is not None else 10**9
    if not 1 <= int(steps) <= limit:
        raise UsageError(f"perturb_steps must be in 1..{limit}, got {steps}")
    if int(start) >= limit:
        raise UsageError(f"perturb_start={start} is past the episode's {limit} steps")
    return Perturbation(kind, int(start), int(steps), size)


def random_perturbation(rng: np.random.Generator, index: int, kinds: tuple[str, ...] = DEMONSTRATED,
                        tilt: tuple[float, float] = TILT_SIZE) -> Perturbation:
    """The perturbation of a demonstration set's `index`-th perturbed episode: `kinds` in turn, so every kind is
    equally represented; start, length and size drawn around what the closed-loop constraints do to a policy (the
    first 15-25 steps; a hand 5-10 cm off its path, or turned by `tilt` radians either way)."""
    kind = kinds[index % len(kinds)]
    start = int(rng.integers(0, 30, endpoint=True))
    steps = int(rng.integers(10, 25, endpoint=True))
    side = rng.choice([-1.0, 1.0])
    size = {"raise": rng.uniform(0.04, 0.10), "shift": rng.uniform(0.03, 0.07) * side,
            "slow": rng.uniform(0.2, 0.5), "tilt": rng.uniform(*tilt) * side}.get(kind)
    return Perturbation(kind, start, steps, None if size is None else float(size))


def parse_tilt_size(value) -> tuple[float, float]:
    """`tilt_size=[low,high]` (radians) -> (low, high), within the tilt perturbation's allowed sizes; else a one-line
    UsageError."""
    _, (lowest, highest), meaning = KINDS["tilt"]
    try:
        low, high = (float(v) for v in value)
    except (TypeError, ValueError):
        raise UsageError(f"tilt_size must be [low,high], got {value!r}") from None
    if not lowest < low <= high <= highest:
        raise UsageError(f"tilt_size=[{low:g},{high:g}] out of range: {meaning}, {lowest:g} < low <= high <= {highest:g}")
    return low, high
