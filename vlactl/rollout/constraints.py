"""Closed-loop constraints of SPEC.md §3: what each one asks, over which window, and how it is judged and steered.

A constraint is `<feature>=<value>`: `gripper=open|closed`, `height=low|high`, `speed=low|high`. It holds over the
first `window` policy steps (15, 15 and 25 by default). Per step it is *satisfied* when
- gripper: the commanded gripper action has the wanted sign (LIBERO: -1 opens, +1 closes; 0, hold, is neither);
- height: the end-effector z is below (low) / above (high) its value at the episode's first policy step;
- speed: the end-effector speed is below (low) / above (high) a threshold, by default the median speed of the
  training demonstrations.
For control, each maps to a box: with `box=action` (the default) on what the policy is about to do, recomputed at
every re-plan from the current state (`action_bound`: the gripper command's side, a discrete-time barrier on the
commanded dz, the commanded speed); with `box=state` on one probe's reading of the state: the gripper-action logit
beyond +-`logit_margin`, the z reading on the wanted side of the start height, the speed reading on the wanted side of
the threshold. Several constraints at once (`[height=high,speed=low]`, one per feature: `parse_constraints`) are
each judged in their own window, filtered together, and steered in one multi-box QP (docs/steering.md, "Several
constraints"). Pure functions: no model, no simulator.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from vlactl.env.features import TRANSLATION
from vlactl.errors import UsageError

# feature -> (allowed values, default window, the step-table column judged = the probe feature box=state steers,
#             the probe features box=action steers: read-outs of the action the policy is about to take (speed: the
#             commanded translation, pushed along its own direction, `push_weights`),
#             the action read-outs box=action holds by default: those the constraint should leave alone; not dyaw
#             for the gripper: held with the shipped probes it kept the gripper from closing, docs/steering.md)
KINDS = {
    "gripper": (("open", "closed"), 15, "gripper_action", ("gripper_action",), TRANSLATION),
    "height": (("low", "high"), 15, "z", ("dz",), ("dx", "dy", "gripper_action")),
    "speed": (("low", "high"), 25, "speed", TRANSLATION, ("gripper_action",)),
}
BOXES = ("action", "state")
PROMPTS = {  # what the prompting baseline appends to the instruction
    ("gripper", "open"): "keep the gripper open",
    ("gripper", "closed"): "keep the gripper closed",
    ("height", "low"): "stay low",
    ("height", "high"): "stay high",
    ("speed", "low"): "move slowly",
    ("speed", "high"): "move fast",
}


@dataclass(frozen=True)
class Constraint:
    feature: str
    value: str
    window: int

    @property
    def name(self) -> str:
        return f"{self.feature}={self.value}"

    @property
    def probe_feature(self) -> str:
        return KINDS[self.feature][2]

    @property
    def action_features(self) -> tuple[str, ...]:
        return KINDS[self.feature][3]

    @property
    def quantity_feature(self) -> str:
        """The one probe feature that reads the bounded quantity itself (gripper_action, dz, speed): what the fixed
        pushes, alpha and meandiff, push along."""
        features = self.action_features
        return features[0] if len(features) == 1 else self.feature

    @property
    def holds(self) -> tuple[str, ...]:
        return KINDS[self.feature][4]

    @property
    def upper(self) -> bool:
        """Whether the constraint keeps the quantity above its reference (closed, high) rather than below it."""
        return self.value in ("closed", "high")


def _allowed() -> str:
    return ", ".join(f"{f}={'|'.join(values)}" for f, (values, *_) in KINDS.items())


def parse_constraint(text: str, window: int | None = None) -> Constraint | None:
    """`gripper=open` -> Constraint; `none` -> None. A bad feature or value is a UsageError naming what is allowed."""
    if text in (None, "", "none"):
        return None
    feature, sep, value = str(text).partition("=")
    if not sep or feature not in KINDS or value not in KINDS[feature][0]:
        raise UsageError(f"unknown constraint {text!r}; allowed: none, {_allowed()}")
    window = KINDS[feature][1] if window is None else int(window)
    if window < 1:
        raise UsageError(f"constraint window must be >= 1 step, got {window}")
    return Constraint(feature, value, window)


def parse_constraints(text, window: int | None = None) -> tuple[Constraint, ...]:
    """`none` -> (); `gripper=open` -> (Constraint,); `[height=high,speed=low]` (or `height=high,speed=low`, or a
    list) -> one Constraint per feature, in KINDS order (the canonical order: `[speed=low,height=high]` is the same
    run). `window` applies to each. An unknown constraint in the list, two on one feature, an empty list or `none`
    inside a list is a one-line UsageError naming the value and what is allowed."""
    if text is None:
        return ()
    if isinstance(text, str):
        body = text.strip()
        listed = body.startswith("[") or body.endswith("]")
        if listed and not (body.startswith("[") and body.endswith("]")):
            raise UsageError(f"constraint={text!r}: unbalanced brackets; write constraint=[height=high,speed=low]")
        body = body[1:-1] if listed else body
        if not listed and body in ("", "none"):
            return ()
        pieces = [piece.strip() for piece in body.split(",")] if body.strip() else []
    else:  # a list from a config file
        pieces, listed = [str(piece).strip() for piece in text], True
    if not pieces:
        raise UsageError(f"constraint={text!r} names no constraint; give one or more of {_allowed()} "
                         f"(e.g. constraint=[height=high,speed=low]), or constraint=none")
    if len(pieces) == 1 and not listed:
        return (parse_constraint(pieces[0], window),)
    found: dict[str, Constraint] = {}
    for piece in pieces:
        if piece in ("", "none"):
            raise UsageError(f"constraint={text!r}: {piece or 'an empty entry'!r} cannot be in a list of "
                             f"constraints; allowed in a list: {_allowed()}")
        feature, _, value = piece.partition("=")
        if feature not in KINDS or value not in KINDS[feature][0]:
            raise UsageError(f"unknown constraint {piece!r} in constraint={text}; allowed: {_allowed()}")
        constraint = parse_constraint(piece, window)
        if constraint.feature in found:
            raise UsageError(f"constraint={text}: two constraints on {constraint.feature} "
                             f"({found[constraint.feature].name}, {constraint.name}); one per feature")
        found[constraint.feature] = constraint
    return tuple(found[f] for f in KINDS if f in found)


def as_constraints(constraint) -> tuple[Constraint, ...]:
    """A Constraint, None or a sequence of them, as a tuple."""
    if constraint is None:
        return ()
    return (constraint,) if isinstance(constraint, Constraint) else tuple(constraint)


def constraint_name(constraints) -> str:
    """What tables and summaries call the run's constraints: `height=high,speed=low`, `gripper=open`, or `none`."""
    return ",".join(c.name for c in as_constraints(constraints)) or "none"


def held_by_default(constraints) -> tuple[str, ...]:
    """The action read-outs box=action holds by default: those every constraint leaves alone (the intersection of
    their KINDS hold tuples), less the features any of them steers."""
    constraints = as_constraints(constraints)
    if not constraints:
        return ()
    steered = {f for c in constraints for f in c.action_features}
    return tuple(f for f in constraints[0].holds if all(f in c.holds for c in constraints) and f not in steered)


START_GRIPPER = ("auto", "open", "closed")
FAVOURED_METHODS = ("none", "prompt")  # the paper's baselines, which get the gripper constraint's state to start from


def start_gripper(setting: str, constraint, method: str) -> str:
    """The gripper state an episode settles in: `open` or `closed` as asked, or for `auto` the paper's protocol
    (§V-B): under a gripper constraint (alone or among others), no intervention and prompting start in the wanted
    state ("a favourable initial condition"); everything else starts open, as LIBERO does."""
    if setting != "auto":
        return setting
    gripper = [c for c in as_constraints(constraint) if c.feature == "gripper"]
    return gripper[0].value if gripper and method in FAVOURED_METHODS else "open"


def reference(constraint: Constraint, start_z: float, speed_threshold: float) -> float:
    """The level a step is compared with: 0 for the gripper action, the start height, or the speed threshold."""
    return {"gripper": 0.0, "height": start_z, "speed": speed_threshold}[constraint.feature]


def box(constraint: Constraint, level: float, logit_margin: float = 2.0) -> tuple[float, float]:
    """[zmin, zmax] on the probe reading that says 'satisfied' (for the gripper, on the gripper-action logit)."""
    if constraint.feature == "gripper":
        return (logit_margin, math.inf) if constraint.upper else (-math.inf, -logit_margin)
    return (level, math.inf) if constraint.upper else (-math.inf, level)


GRIPPER_BOUND = 0.5


@dataclass(frozen=True)
class Bounds:
    """What turns a constraint into a bound on the action (`action_bound`), one run's settings: the speed threshold
    (m/s) and the hand's motion per unit of translation command per step (`metres_per_unit`), both measured from the
    demonstrations, the height barrier's rate (`decay`: the share of the remaining distance to its level a step may
    close) and the metres its level lies inside the allowed side (`height_margin`), and the share of the threshold
    the speed bound lies inside it (`speed_margin`: a hand held exactly at the threshold wobbles across it; filter
    speed=low at the threshold itself: mean speed 0.194 m/s, 59% of window steps satisfied)."""

    speed_threshold: float = 0.0
    metres_per_unit: float = 0.0
    decay: float = 0.5
    height_margin: float = 0.0
    speed_margin: float = 0.1

    def level(self, constraint: Constraint, start_z: float) -> float:
        return reference(constraint, start_z, self.speed_threshold)


def action_bound(constraint: Constraint, z: float, level: float, bounds: Bounds, steps: int = 1) -> tuple[float, float]:
    """[lo, hi] on the action quantity the constraint acts on (`action_quantity`), for the next `steps` actions
    (docs/steering.md):
    - gripper: every gripper command about to be executed past +-0.5 on the wanted side (it then executes as close /
      open, not as hold);
    - height: the mean commanded dz, as a discrete-time barrier on h = +-(z - z0) >= 0: with z' = z + s dz (s =
      `bounds.metres_per_unit`), h' >= (1 - decay) h per step, i.e. over k steps for high
      mean dz >= -(1 - (1 - decay)^k) (z - z0) / (k s) (k = 1: dz >= -decay (z - z0) / s), and the mirror image for
      low: the hand may approach the start height by `decay` of its distance per step, so it slows towards the bound
      instead of bouncing off it;
    - speed: the commanded translation's norm, |(dx, dy, dz)| <= (low) or >= (high) threshold dt / s, the share
      `speed_margin` inside the threshold (the hand's speed per unit of command varies from step to step).
    `height_margin` (metres) moves the height barrier's level that far to the allowed side of z0, so a hand that
    settles at the level is judged satisfied (z >= z0) despite the few millimetres it wobbles. A bound the formula
    puts on the wrong side of 0 (the hand already past the level) asks for a move back."""
    from vlactl.env.features import CONTROL_DT

    if constraint.feature == "gripper":  # past +-0.5: the command snaps to close / open, not to hold (0)
        return (GRIPPER_BOUND, math.inf) if constraint.upper else (-math.inf, -GRIPPER_BOUND)
    if constraint.feature == "height":
        rate = (1 - (1 - bounds.decay) ** steps) / (steps * bounds.metres_per_unit)
        level = level + bounds.height_margin if constraint.upper else level - bounds.height_margin
        if constraint.upper:
            return (-rate * (z - level), math.inf)
        return (-math.inf, rate * (level - z))
    inside = 1 + bounds.speed_margin if constraint.upper else 1 - bounds.speed_margin
    norm = inside * level * CONTROL_DT / bounds.metres_per_unit
    return (norm, math.inf) if constraint.upper else (0.0, norm)


def action_quantity(constraint: Constraint, actions, decay: float = Bounds.decay):
    """What `action_bound` bounds, over the actions about to be executed ([k, 7]): the gripper command least on the
    wanted side (every one of them is judged, so every one must snap to close / open), the mean translation norm,
    or for height the barrier's worst step: every step j <= k of the chunk must keep the barrier (the hand is judged
    at each, and a chunk whose mean dz keeps it can dip past the bound on its way), i.e. for high
    mean(dz[:j]) >= -r_j (z - z0) with r_j = (1 - (1 - decay)^j) / (j s); scaled by r_k / r_j each step's mean
    compares with the k-step bound of `action_bound`, so q is the least (high) / largest (low) of those scaled
    prefix means, and the chunk's mean dz when the prefixes keep pace with it."""
    import numpy as np

    actions = np.asarray(actions, dtype=np.float64).reshape(-1, 7)
    if constraint.feature == "gripper":
        return float(actions[:, 6].min() if constraint.upper else actions[:, 6].max())
    if constraint.feature == "height":
        j = np.arange(1, len(actions) + 1)
        reach = (1 - (1 - decay) ** j) / j  # r_j s
        scaled = np.cumsum(actions[:, 2]) / j * (reach[-1] / reach)
        return float(scaled.min() if constraint.upper else scaled.max())
    return float(np.linalg.norm(actions[:, :3], axis=1).mean())


def push_weights(constraint: Constraint, actions) -> dict[str, float]:
    """How a unit reading shift of the constraint's push is shared among its probes (`Constraint.action_features`):
    all of it for one feature; for speed, along the predicted translation's own direction (mean over the actions about
    to be executed), so the push slows or speeds the hand without turning it."""
    import numpy as np

    features = constraint.action_features
    if len(features) == 1:
        return {features[0]: 1.0}
    motion = np.asarray(actions, dtype=np.float64).reshape(-1, 7)[:, :3].mean(0)
    norm = float(np.linalg.norm(motion))
    unit = motion / norm if norm > 1e-6 else np.full(3, 3 ** -0.5)
    return dict(zip(features, map(float, unit)))


def filter_action(constraint: Constraint, action, z: float, level: float, bounds: Bounds):
    """`method=filter`: the executed action changed as little as possible (in L2) so that its constrained quantity
    lies in `action_bound`: the gripper command forced to open / close, dz clipped to the barrier, the translation
    scaled to the speed bound (along its own direction). The oracle an action-space safety filter gives."""
    import numpy as np

    out = np.array(action, dtype=np.float64)
    lo, hi = action_bound(constraint, z, level, bounds)
    if constraint.feature == "gripper":
        out[6] = 1.0 if constraint.upper else -1.0
    elif constraint.feature == "height":
        out[2] = float(np.clip(out[2], lo, hi))
    else:
        norm = float(np.linalg.norm(out[:3]))
        wanted = float(np.clip(norm, lo, hi))
        if norm > 1e-9 and wanted != norm:
            out[:3] *= wanted / norm
    return out


def pausable(constraint: Constraint) -> bool:
    """Whether stopping the arm satisfies the constraint: height either way (a still hand keeps its side of the
    level), speed=low (a still hand is slow)."""
    return constraint.feature == "height" or constraint.name == "speed=low"


# control with pause: the read-outs the stop pushes (those of them a probe run has). The tilt (droll, dpitch) is left to
# the policy: pushing or holding its read-outs spoiled the stop; what keeps it is a stop fitted with the other action
# features regressed out (shipped as data/probes/<model>/stop; docs/steering.md).
STOP_READOUTS = ("dx", "dy", "dz", "dyaw")
PAUSE_NORM = 0.1  # control with pause: the commanded translation's mean norm a stop may keep (action units)


def stop_bound(bounds: dict) -> tuple[float, float]:
    """Control with `pause`: the bound on the commanded translation's mean norm (the speed quantity) that stands the
    arm still where a pausable constraint binds: at most PAUSE_NORM beyond the rise (or descent) the height barrier
    asks for (`bounds`: feature -> the [lo, hi] of `action_bound` at this re-plan). The push's counterpart of
    `pause_action`, which also stops the yaw read-out where the probe run has it (ConstrainedAgent._stop)."""
    lo, hi = bounds.get("height", (-math.inf, math.inf))
    return 0.0, PAUSE_NORM + max(lo, -hi, 0.0)


def pause_action(action, height_bound: tuple[float, float] | None = None):
    """The arm stopped: translation and rotation commands zero, except the dz nearest zero that the height barrier
    allows (a rise while the hand is below the level), the gripper command as given. What `pause` does instead of the
    smallest change of the bounded quantity when a pausable constraint binds: measured, a hand held still for the
    window keeps the task, a hand kept up by dz alone moves on across and misses the grasp (docs/steering.md)."""
    import numpy as np

    out = np.array(action, dtype=np.float64)
    out[:6] = 0.0
    if height_bound is not None:
        out[2] = float(np.clip(0.0, *height_bound))
    return out


def filter_actions(constraints, action, z: float, start_z: float, bounds: Bounds, pause: bool = False):
    """`filter_action` for several constraints at once. The gripper command is forced apart from the translation.
    Height and speed both bound the translation: the result is the one nearest the action (L2) that keeps dz in the
    barrier and the norm in the speed bound, among the speed filter alone, the height filter alone, and dz clipped
    with (dx, dy) scaled to the speed bound (for speed=low, the exact projection onto the feasible set). When no
    translation satisfies both (speed=low below the rise the barrier asks for), the height barrier wins: dz clipped,
    (dx, dy) as near the speed bound as they can get (zero).
    With `pause`, an action that breaks a `pausable` constraint's bound is replaced by `pause_action` (the gripper
    still forced by a gripper constraint)."""
    import numpy as np

    constraints = as_constraints(constraints)
    by_feature = {c.feature: c for c in constraints}
    if pause:
        binding = {c.feature: action_bound(c, z, bounds.level(c, start_z), bounds) for c in constraints if pausable(c)}
        if any(not lo <= action_quantity(by_feature[f], action, bounds.decay) <= hi for f, (lo, hi) in binding.items()):
            out = pause_action(action, binding.get("height"))
            return filter_action(by_feature["gripper"], out, z, 0.0, bounds) if "gripper" in by_feature else out
    if len(constraints) == 1 or not {"height", "speed"} <= set(by_feature):
        out = np.array(action, dtype=np.float64)
        for c in constraints:
            out = filter_action(c, out, z, bounds.level(c, start_z), bounds)
        return out
    height, speed = by_feature["height"], by_feature["speed"]
    out = filter_action(by_feature["gripper"], action, z, 0.0, bounds) if "gripper" in by_feature \
        else np.array(action, dtype=np.float64)
    (lo, hi), (slow, fast) = (action_bound(c, z, bounds.level(c, start_z), bounds) for c in (height, speed))
    v = out[:3].copy()

    def along(w):  # the speed filter: scaled along its own direction
        norm = float(np.linalg.norm(w))
        wanted = float(np.clip(norm, slow, fast))
        return w * (wanted / norm) if norm > 1e-9 and wanted != norm else w

    def level(w):  # dz kept, (dx, dy) scaled so the norm reaches the speed bound (zero where it cannot)
        wanted = float(np.clip(np.linalg.norm(w), slow, fast))
        flat, room = float(np.linalg.norm(w[:2])), wanted ** 2 - w[2] ** 2
        out = w.copy()
        if room < 0:
            out[:2] = 0.0
        elif flat > 1e-9:
            out[:2] *= np.sqrt(room) / flat
        return out

    def feasible(w):
        norm = float(np.linalg.norm(w))
        return lo - 1e-9 <= w[2] <= hi + 1e-9 and slow - 1e-9 <= norm <= fast + 1e-9

    clipped = v.copy()
    clipped[2] = float(np.clip(v[2], lo, hi))
    candidates = [w for w in (along(v), clipped, level(clipped), along(clipped)) if feasible(w)]
    out[:3] = min(candidates, key=lambda w: float(np.linalg.norm(w - v))) if candidates else level(clipped)
    return out


def filter_hook(constraint, bounds: Bounds, pause: bool = False):
    """A fresh per-episode step hook for `run_episode` that filters every action of the constraint window (several
    constraints: each over its own window, together where windows overlap, `filter_actions`, with `pause` stopping
    the arm where a pausable constraint binds); the start height is the hand's z at the first policy step."""
    constraints = as_constraints(constraint)
    start = {}

    def hook(t: int, obs, action):
        z = float(obs.state[2])
        start.setdefault("z", z)
        active = [c for c in constraints if t < c.window]
        if not active:
            return action
        return filter_actions(active, action, z, start["z"], bounds, pause)

    return hook


def prompted(instruction: str, constraint) -> str:
    """The prompting baseline: the constraint said in words after the task (several: each, joined by 'and')."""
    return " and ".join([instruction, *(PROMPTS[(c.feature, c.value)] for c in as_constraints(constraint))])


def judge_steps(constraint: Constraint, steps, start_z: float, speed_threshold: float):
    """Adds to a rollout's step table (one episode): in_window, constraint_value, constraint_level, satisfied
    (missing outside the window). Returns the table and the episode's satisfaction: the fraction of its window steps
    satisfied (NaN if the episode ended before the window began, which cannot happen with window >= 1)."""
    import numpy as np
    import pandas as pd

    level = reference(constraint, start_z, speed_threshold)
    values = steps[constraint.probe_feature].to_numpy(dtype=float)  # the step table names columns like the probes
    inside = steps["t"].to_numpy() < constraint.window
    if constraint.feature == "gripper":  # the command's sign: 0 holds the fingers where they are, which is neither
        ok = values > level if constraint.upper else values < level
    else:
        ok = values >= level if constraint.upper else values <= level
    steps = steps.assign(
        in_window=inside, constraint_value=values, constraint_level=level,
        satisfied=pd.array(np.where(inside, ok, False), dtype="boolean"),
    )
    steps.loc[~inside, "satisfied"] = pd.NA
    return steps, float(ok[inside].mean()) if inside.any() else float("nan")


JUDGED = ("in_window", "constraint_value", "constraint_level", "satisfied")  # the columns judge_steps adds


def judge_all(constraints, steps, start_z: float, speed_threshold: float):
    """`judge_steps` for one constraint or several. Several: each constraint judged in its own window, its columns
    suffixed by its feature (`satisfied_height`, ...); `in_window` is then any constraint's window and `satisfied`
    that every constraint whose window covers the step is satisfied. Returns the table, the episode's satisfaction
    (the share of window steps satisfied) and {feature: that constraint's own satisfaction}."""
    import numpy as np
    import pandas as pd

    constraints = as_constraints(constraints)
    if len(constraints) == 1:
        steps, satisfaction = judge_steps(constraints[0], steps, start_z, speed_threshold)
        return steps, satisfaction, {constraints[0].feature: satisfaction}
    columns, own = {}, {}
    covered = np.zeros(len(steps), dtype=bool)
    every = np.ones(len(steps), dtype=bool)
    for c in constraints:
        judged, own[c.feature] = judge_steps(c, steps, start_z, speed_threshold)
        columns.update({f"{column}_{c.feature}": judged[column] for column in JUDGED})
        inside = judged["in_window"].to_numpy(dtype=bool)
        covered |= inside
        every &= ~inside | judged["satisfied"].fillna(False).to_numpy(dtype=bool)
    satisfied = pd.array(np.where(covered, every, False), dtype="boolean")
    satisfied[~covered] = pd.NA
    steps = steps.assign(in_window=covered, satisfied=satisfied, **columns)
    return steps, float(every[covered].mean()) if covered.any() else float("nan"), own
