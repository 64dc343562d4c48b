"""A VLA agent under a constraint: `prompt` says it in the instruction; `control`, `alpha` and `meandiff` steer the
constrained probe's layers with a `Steerer` at every prediction made inside the constraint window (SPEC.md §3):
the minimal controller, a fixed push along the probe direction, or a fixed push along the difference of the class
means of the training activations.

`control` with `box=action` (the default) bounds what the policy is about to do: at each re-plan in the window it
predicts unsteered, and only when the predicted actions break the state-aware bound of `action_bound` (a barrier
on dz for height) does it predict again with the minimal push that shifts the steering probe's reading by delta at
every steered layer, delta found by a secant search on the predicted quantity (the same sampling noise each pass), a
few passes at most. With `box=state` it keeps the probe's reading of the state in a fixed box at every forward.

Under several constraints (control with box=action only) each has its own bound, steering probes and window: a
re-plan pushes only if some bound breaks, and then searches the shift of each broken constraint in turn, with the
probes of the others held at their current shifts by relative boxes of the same multi-box QP.

The box depends on the episode (the start height for `height=`), so it is set at each reset. The agent keeps, per
step, the probe readings before and after the intervention at the prediction made on that step.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vlactl.env.features import ACTION_FEATURES
from vlactl.rollout.agents import VLAAgent
from vlactl.rollout.bracket import Bracket
from vlactl.rollout.constraints import (GRIPPER_BOUND, KINDS, STOP_READOUTS, Bounds, Constraint, action_bound,
                                       action_quantity, as_constraints, box, pausable, prompted, push_weights,
                                       stop_bound)
from vlactl.steering.steer import Constraint as ProbeBox
from vlactl.steering.steer import Steerer

METHODS = ("none", "prompt", "control", "alpha", "meandiff", "filter")
STEERING = ("control", "alpha", "meandiff")
# Per step with a steered prediction: the reading at the first forward through the first steered layer, and the
# push over every steered layer and forward of that prediction (a hybrid steers each expert layer at every denoising
# step): its summed norm and the share of those forwards it acted in.
# box=action adds the bounded action quantity before and after the push, its bound at that re-plan, the number of
# steered re-predictions it took, and (pause) whether the re-plan was bounded to a stop, with the commanded
# translation's mean norm before and after that push.
READING_COLUMNS = ("reading_before", "reading_after", "u_norm", "control_active", "u_norm_all", "active_share",
                   "action_before", "action_after", "bound_lo", "bound_hi", "passes", "paused", "stop_before",
                   "stop_after")
# Under several constraints, the columns of each constraint get its feature as a suffix (`bound_lo_height`).
PER_CONSTRAINT = ("reading_before", "reading_after", "action_before", "action_after", "bound_lo", "bound_hi")
STOP_PROBE = 0.25  # pause: the finite-difference step of the stop's per-read-out shifts, a share of the shift so far
STOP_STEPS = 3  # pause: Newton steps of the stop's push after its finite differences
SATURATED_GROWTH = 3  # pause: times a read-out's finite-difference step grows x4 while its commands stay clipped
CLIPPED = 0.999  # an action command this near the [-1, 1] box's edge is clipped (the models clip their outputs)
BAND = 0.15  # a pushed prediction is taken when its quantity lies between the bound and this far past it (action
             # units): the minimal push puts it at the bound, not wherever a saturating push lands


@dataclass(frozen=True)
class Steering:
    """How a run intervenes: the method, and for control/alpha the probes (one per steered layer) and sizes."""

    method: str
    probes: tuple = ()  # vlactl.steering.probes.Probe, all of the constraint's probe feature
    directions: dict | None = None  # meandiff: layer -> unit direction towards the 'closed / high' side
    alpha: float = 4.0
    logit_margin: float = 2.0
    bounds: Bounds = Bounds()  # the speed threshold (judging, box=state) and, for filter and box=action, the rest
    box: str = "action"  # control: bound the predicted action (action) or the probe's reading of the state (state)
    passes: int = 5  # box=action: steered re-predictions at most per re-plan
    holds: tuple = ()  # control: probes (any steered layer, other features) whose readings the push leaves alone
    hold_tolerance: float = 0.0
    pause: bool = False  # stop the arm where a pausable constraint binds: filter `pause_action`, control `stop_bound`

    @property
    def label(self) -> str:
        return method_label(self.method, self.pause)


def method_label(method: str, pause: bool) -> str:
    """What tables, figures and run folders call a method: `filter+pause` for the pausing filter (as a folder name,
    `filter-pause`), else the method."""
    return f"{method}+pause" if pause else method


def reading_columns(constraints) -> tuple[str, ...]:
    """The step table's reading columns: READING_COLUMNS for one constraint; for several, the push's own columns once
    and PER_CONSTRAINT suffixed by each constraint's feature."""
    constraints = as_constraints(constraints)
    if len(constraints) <= 1:
        return READING_COLUMNS
    shared = tuple(c for c in READING_COLUMNS if c not in PER_CONSTRAINT)
    return shared + tuple(f"{column}_{c.feature}" for c in constraints for column in PER_CONSTRAINT)


class ConstrainedAgent(VLAAgent):
    def __init__(
        self, vla, constraint, steering: Steering, replan_every: int | None = None, snap_gripper: bool = True,
    ):
        """`constraint`: a Constraint, or several (a tuple: control with box=action, prompt; one per feature)."""
        super().__init__(vla, replan_every, snap_gripper)
        self.constraints = as_constraints(constraint)
        self.constraint, self.steering = self.constraints[0], steering
        self.readings: dict[int, dict] = {}
        # each constraint's steering probes: those of its action read-out (features differ: one constraint a feature);
        # with pause the stop's: the translation and yaw read-outs (`_stop`)
        mixed = len(self.constraints) > 1 or steering.pause
        self._probes = {c.feature: tuple(p for p in steering.probes if p.feature in c.action_features) if mixed
                        else steering.probes for c in self.constraints}
        if steering.pause:
            self._probes["speed"] = tuple(p for p in steering.probes if p.feature in STOP_READOUTS)
        if "gripper" not in self._probes:  # what keeps a held gripper on the action (`_gripper_kept`)
            self._probes["gripper"] = tuple(p for p in steering.holds if p.feature == "gripper_action")

    def reset(self, env, obs, seed: int | None = None) -> None:
        super().reset(env, obs, seed)
        if self.steering.method == "prompt":
            self._instruction = prompted(env.instruction, self.constraints)
        self._levels = {c.feature: self.steering.bounds.level(c, float(obs.state[2])) for c in self.constraints}
        level = self._levels[self.constraint.feature]
        zmin, zmax = box(self.constraint, level, self.steering.logit_margin)
        tol = self.steering.hold_tolerance
        held = [ProbeBox(p, -tol, tol, relative=True) for p in self.steering.holds]
        self._boxes = [ProbeBox(p, zmin, zmax) for p in self.steering.probes] + held  # per layer, the constraint first
        self._held, self._level = held, level
        self._t, self.readings = 0, {}

    def act(self, obs):
        t, self._t = self._t, self._t + 1
        inside = any(t < c.window for c in self.constraints)
        steer = self.steering.method in STEERING and inside and not self._queue
        if not steer:
            return super().act(obs)
        if self.steering.method == "control" and self.steering.box == "action":
            self._queue = list(self.snap(self._bounded_chunk(obs, t)))
            return self._queue.pop(0)
        # alpha pushes towards the constraint: up the probe direction for closed/high, down for open/low
        alpha = self.steering.alpha if self.constraint.upper else -self.steering.alpha
        method = "direction" if self.steering.method == "meandiff" else self.steering.method
        with Steerer(self.vla, self._boxes, method=method, alpha=alpha, directions=self.steering.directions) as steerer:
            action = super().act(obs)
        self.readings[t] = push_record(steerer.log)
        return action

    def _bounded_chunk(self, obs, t: int):
        """The next actions, pushed only if they break this re-plan's action bounds (box=action): each constraint in
        its window bounds its own quantity; the broken ones are searched in turn (KINDS order), the others' probes held
        at their shifts so far, and once more, from its shift so far, one that a later push broke."""
        plan, several = self.steering, len(self.constraints) > 1
        named = [c for c in self.constraints if t < c.window]
        start = self.vla.sampling_state()
        actions = self.predict(obs)
        drawn = self.vla.sampling_state()
        active = named + self._gripper_kept(actions, t)
        bounds = {c.feature: action_bound(c, float(obs.state[2]), self._levels.get(c.feature, 0.0), plan.bounds,
                                          self.replan_every) for c in active}
        # pause: where a pausable bound breaks, the translation is bounded to a stop too (speed=low's bound becomes it)
        paused = plan.pause and any(pausable(c) and not self._inside(c, bounds, actions) for c in named)
        if paused:
            bounds["speed"] = stop_bound(bounds)
            active += [] if "speed" in {c.feature for c in active} else [Constraint("speed", "low", t + 1)]
        before = {c.feature: self._quantity(c, actions) for c in active}
        self._weights = {c.feature: push_weights(c, actions) for c in active}  # from the unsteered prediction
        row = {"passes": 0, "u_norm": 0.0, "control_active": False, "u_norm_all": 0.0, "active_share": 0.0,
               "paused": paused}
        shifts = {c.feature: 0.0 for c in active}
        log, passes, kept = None, 0, {}
        for again in (False, True):  # the second sweep: only constraints a later push broke
            for c in active:
                (lo, hi), quantity = bounds[c.feature], self._quantity(c, actions)
                if lo <= quantity <= hi or (again and not kept[c.feature]):
                    kept.setdefault(c.feature, lo <= quantity <= hi)
                    continue
                actions, shifts[c.feature], used, log = self._search(obs, c, bounds, quantity, shifts, active, start)
                if paused and c.feature == "speed" and not self._inside(c, bounds, actions):
                    actions, shifts[c.feature], more, log = self._stop(obs, c, bounds, shifts, active, start,
                                                                      (actions, log))
                    used += more
                passes += used
                kept[c.feature] = self._inside(c, bounds, actions)
            if len(active) == 1:
                break
        if log is not None:
            self.vla.set_sampling_state(drawn)
            row = {**row, **push_record(log, [c.feature for c in named] if several else None), "passes": passes}
        if paused:  # the commanded translation's mean norm, unsteered and as pushed towards the stop
            stop = next(c for c in active if c.feature == "speed")
            row.update(stop_before=before["speed"], stop_after=self._quantity(stop, actions))
        for c in named:
            (lo, hi), after = bounds[c.feature], self._quantity(c, actions)
            suffix = f"_{c.feature}" if several else ""
            row.update({f"action_before{suffix}": before[c.feature], f"bound_lo{suffix}": lo,
                        f"bound_hi{suffix}": hi, f"action_after{suffix}": after})
        self.readings[t] = row
        return actions

    def _search(self, obs, constraint: Constraint, bounds: dict, before: float, shifts: dict, active: list, start):
        """The push that brings `constraint`'s quantity across its bound (`bounds`: feature -> [lo, hi] of every
        active constraint): a bracketing search on its probes' reading shift from its shift so far, every pass
        predicted again from the same sampling state `start`; the other active constraints' probes keep their
        `shifts` (relative boxes), the holds their readings. Of the passes inside its bound, the one that breaks the
        fewest other bounds, then nearest the target, is taken; if none is, the one nearest its bound. Returns
        (actions, shift, passes, log)."""
        plan = self.steering
        lo, hi = bounds[constraint.feature]
        others = [c for c in active if c is not constraint]
        below = before < lo
        target = lo + BAND / 2 if below else hi - BAND / 2  # inside the band past the bound
        accept = (lo, lo + BAND) if below else (hi - BAND, hi)
        bracket = Bracket(shifts[constraint.feature], before - target)
        passes, best = 0, None
        for _ in range(plan.passes):
            shift = bracket.shift
            self.vla.set_sampling_state(start)
            boxes = self._push_boxes({**shifts, constraint.feature: shift}, active)
            with Steerer(self.vla, boxes, method="control") as steerer:
                actions = self.predict(obs)
            quantity, passes, last = self._quantity(constraint, actions), passes + 1, (actions, shift, steerer.log)
            broken = sum(not self._inside(c, bounds, actions) for c in others)
            rank = (self._excess(constraint, bounds, actions), broken, abs(quantity - target))
            if best is None or rank < best[0]:
                best = (rank, last)
            if accept[0] <= quantity <= accept[1] or not bracket.update(quantity - target):
                break
        actions, shift, log = best[1]  # a push that saturates the actions can land anywhere: the best pass seen
        return actions, shift, passes, log

    def _stop(self, obs, stop: Constraint, bounds: dict, shifts: dict, active: list, start, found):
        """pause: the stop's push from where the search along the predicted motion left it (`found`: its actions and
        log). That search turns the motion's own component to zero but leaves the others: pushing the translation
        read-outs along the motion also turns it sideways (offline, the mean command's norm goes 0.76 -> 0.42 at
        best), and the hand keeps turning. So each stop read-out (translation, and yaw where the probes have it)
        gets its own shift: their effect on every executed action's commands measured by finite differences, then
        STOP_STEPS Newton steps (Broyden updates) towards the stop at each step (zero, but the dz the height barrier
        asks) in least squares: a chunk whose commands only cancel on average still moves the hand. Of the passes,
        the one nearest the speed bound, then nearest the stop over all read-outs (yaw included), is taken. The
        shifts are kept as the stop's push weights (shift 1). Returns (actions, 1.0, passes, log)."""
        features = [f for f in STOP_READOUTS if any(p.feature == f for p in self._probes["speed"])]
        columns = [ACTION_FEATURES.index(f) for f in features]
        along = self._weights["speed"]
        origin = np.array([shifts["speed"] * along.get(f, 0.0) for f in features])
        lo, hi = bounds.get("height", (-np.inf, np.inf))
        steps = len(np.asarray(found[0]).reshape(-1, 7))
        wanted = np.tile(np.where(np.array(features) == "dz", float(np.clip(0.0, lo, hi)), 0.0), steps)

        def commands(actions):
            return np.asarray(actions, dtype=np.float64).reshape(-1, 7)[:, columns].ravel()

        def rank(actions):
            return self._excess(stop, bounds, actions), float(np.linalg.norm(commands(actions) - wanted))

        best = (rank(found[0]), found[0], found[1], origin)

        def push(vector):
            nonlocal best
            self._weights["speed"] = dict(zip(features, map(float, vector)))
            self.vla.set_sampling_state(start)
            with Steerer(self.vla, self._push_boxes({**shifts, "speed": 1.0}, active), method="control") as steerer:
                actions = self.predict(obs)
            best = min(best, (rank(actions), actions, steerer.log, vector), key=lambda b: b[0])
            return commands(actions)

        now, step = commands(found[0]), STOP_PROBE * max(float(np.abs(origin).max()), 1e-2)
        own, target = now.reshape(-1, len(features)), wanted[:len(features)]
        slopes, passes = [], len(features) + STOP_STEPS
        for i, e in enumerate(np.eye(len(features))):
            # towards the stop, and further while the read-out's own commands sit clipped at the action box's edge
            # (the policy turning at full command: a small push moves nothing there, and the slope would read zero)
            size, clipped = (step if own[:, i].mean() <= target[i] else -step), np.abs(own[:, i]).min() >= CLIPPED
            for grow in range(SATURATED_GROWTH + 1):
                slope = (push(origin + size * e) - now) / size
                moved = np.abs(slope.reshape(own.shape)[:, i] * size).max() > 1e-3
                if not clipped or moved or grow == SATURATED_GROWTH:
                    break
                size, passes = size * 4, passes + 1
            slopes.append(slope)
        jacobian = np.stack(slopes, axis=1)
        vector = origin
        for _ in range(STOP_STEPS):
            move = np.linalg.lstsq(jacobian, wanted - now, rcond=None)[0]
            reached = push(vector + move)
            if move @ move > 0:
                jacobian += np.outer(reached - now - jacobian @ move, move) / (move @ move)
            vector, now = vector + move, reached
        self._weights["speed"] = dict(zip(features, map(float, best[3])))
        return best[1], 1.0, passes, best[2]

    def _excess(self, constraint: Constraint, bounds: dict, actions) -> float:
        """How far the actions' quantity lies outside the constraint's bound (0 inside)."""
        lo, hi = bounds[constraint.feature]
        quantity = self._quantity(constraint, actions)
        return max(lo - quantity, quantity - hi, 0.0)

    def _inside(self, constraint: Constraint, bounds: dict, actions) -> bool:
        return self._excess(constraint, bounds, actions) == 0.0

    def _quantity(self, constraint: Constraint, actions) -> float:
        return action_quantity(constraint, actions, self.steering.bounds.decay)

    def _gripper_kept(self, actions, t: int) -> list:
        """A held gripper read-out kept on the action itself: when the constraints leave the gripper alone and the
        unsteered chunk commands it one way throughout (every command past +-0.5), a constraint keeping it there for
        this re-plan, pushed by the gripper-action hold probes, which it takes over from the holds. A hold on the
        probe's reading alone does not keep the command: pushing speed down at the expert closed the gripper at step 1
        (median) with the gripper-action reading held (rollout, 2026-12-01)."""
        if not self._probes["gripper"] or any(c.feature == "gripper" for c in self.constraints):
            return []
        command = np.asarray(actions, dtype=np.float64).reshape(-1, 7)[:, 6]
        side = "closed" if command.min() >= GRIPPER_BOUND else "open" if command.max() <= -GRIPPER_BOUND else None
        return [] if side is None else [Constraint("gripper", side, t + 1)]

    def _push_boxes(self, shifts: dict, active: list) -> list:
        """Relative boxes for the constraints' reading shifts: each probe shifted by the sum, over the constraints
        that push it, of their shift times its share (`push_weights`; height and speed both push dz), and the holds
        of the probes no constraint pushes."""
        total = {}
        for c in active:
            for p in self._probes[c.feature]:
                probe, shift = total.get((p.layer, p.feature), (p, 0.0))
                weight = self._weights[c.feature].get(p.feature, 0.0)  # the stop's yaw read-out: not speed's
                total[p.layer, p.feature] = (probe, shift + shifts[c.feature] * weight)
        held = [b for b in self._held if (b.layer, b.probe.feature) not in total]  # a pushed probe is not held
        return [ProbeBox(p, shift, shift, relative=True) for p, shift in total.values()] + held


def push_record(log: list[dict], features: list[str] | None = None) -> dict:
    """A steered prediction's reading columns from its Steerer log: the reading of the first steered layer's first
    probe (the constraint's, not a hold's) at the first forward that pushed it (row 0: one observation), and the push
    summed over every forward of that prediction. `features` (several constraints: theirs, `height`, ...): the reading
    of each constraint's probe at its first forward, as `reading_before_<feature>` and `reading_after_<feature>`."""
    first = next(e for e in log if e["box"] == 0)
    pushes = {}  # one per forward of a steered layer: the first entry of its row 0
    for e in log:
        if e["row"] == 0:
            pushes.setdefault(e["forward"], e["u_norm"])
    pushes = list(pushes.values())
    record = {"u_norm": first["u_norm"], "control_active": first["active"], "u_norm_all": sum(pushes),
              "active_share": sum(u > 0 for u in pushes) / len(pushes)}
    if features is None:
        return {"reading_before": first["before"], "reading_after": first["after"], **record}
    for feature in features:
        entry = next((e for e in log if e["row"] == 0 and e["feature"] == KINDS[feature][3][0]), None)
        if entry is not None:
            record.update({f"reading_before_{feature}": entry["before"], f"reading_after_{feature}": entry["after"]})
    return record
