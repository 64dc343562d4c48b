"""A VLA agent under a constraint: `prompt` says it in the instruction; `control`, `alpha` and `meandiff` steer the
constrained probe's layers with a `Steerer` at every prediction made inside the constraint window (SPEC.md §3):
the minimal controller, a fixed push along the probe direction, or a fixed push along the difference of the class
means of the training activations.

The box depends on the episode (the start height for `height=`), so it is set at each reset. The agent keeps, per
step, the probe readings before and after the intervention at the prediction made on that step.
"""

from __future__ import annotations

from dataclasses import dataclass

from vlactl.rollout.agents import VLAAgent
from vlactl.rollout.constraints import Constraint, box, prompted, reference
from vlactl.steering.steer import Constraint as ProbeBox
from vlactl.steering.steer import Steerer

METHODS = ("none", "prompt", "control", "alpha", "meandiff", "filter")
STEERING = ("control", "alpha", "meandiff")
# Per step with a steered prediction: the reading at the first forward through the first steered layer, and the
# push over every steered layer and forward of that prediction (a hybrid steers each expert layer at every denoising
# step): its summed norm and the share of those forwards it acted in.
READING_COLUMNS = ("reading_before", "reading_after", "u_norm", "control_active", "u_norm_all", "active_share")


@dataclass(frozen=True)
class Steering:
    """How a run intervenes: the method, and for control/alpha the probes (one per steered layer) and sizes."""

    method: str
    probes: tuple = ()  # vlactl.steering.probes.Probe, all of the constraint's probe feature
    directions: dict | None = None  # meandiff: layer -> unit direction towards the 'closed / high' side
    alpha: float = 4.0
    logit_margin: float = 2.0
    speed_threshold: float = 0.0
    metres_per_unit: float = 0.0  # filter: hand motion per unit of translation command per step
    barrier_decay: float = 0.5
    holds: tuple = ()  # control: probes (any steered layer, other features) whose readings the push leaves alone
    hold_tolerance: float = 0.0


class ConstrainedAgent(VLAAgent):
    def __init__(
        self, vla, constraint: Constraint, steering: Steering, replan_every: int | None = None,
        snap_gripper: bool = True,
    ):
        super().__init__(vla, replan_every, snap_gripper)
        self.constraint, self.steering = constraint, steering
        self.readings: dict[int, dict] = {}

    def reset(self, env, obs) -> None:
        super().reset(env, obs)
        if self.steering.method == "prompt":
            self._instruction = prompted(env.instruction, self.constraint)
        level = reference(self.constraint, float(obs.state[2]), self.steering.speed_threshold)
        zmin, zmax = box(self.constraint, level, self.steering.logit_margin)
        tol = self.steering.hold_tolerance
        held = [ProbeBox(p, -tol, tol, relative=True) for p in self.steering.holds]
        self._boxes = [ProbeBox(p, zmin, zmax) for p in self.steering.probes] + held  # per layer, the constraint first
        self._t, self.readings = 0, {}

    def act(self, obs):
        t, self._t = self._t, self._t + 1
        steer = self.steering.method in STEERING and t < self.constraint.window and not self._queue
        if not steer:
            return super().act(obs)
        # alpha pushes towards the constraint: up the probe direction for closed/high, down for open/low
        alpha = self.steering.alpha if self.constraint.upper else -self.steering.alpha
        method = "direction" if self.steering.method == "meandiff" else self.steering.method
        with Steerer(self.vla, self._boxes, method=method, alpha=alpha, directions=self.steering.directions) as steerer:
            action = super().act(obs)
        first = steerer.log[0]  # the first forward through the first steered layer (row 0: one observation)
        pushes = [e["u_norm"] for e in steerer.log if e["row"] == 0 and e["feature"] == first["feature"]]  # one per forward
        self.readings[t] = dict(zip(READING_COLUMNS, (first["before"], first["after"], first["u_norm"], first["active"],
                                                      sum(pushes), sum(u > 0 for u in pushes) / len(pushes))))
        return action
