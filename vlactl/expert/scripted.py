"""A scripted pick-and-place expert for LIBERO, driven by privileged object poses.

It reads the target and destination from the task's BDDL goal (e.g. ['on', 'akita_black_bowl_1', 'plate_1']) and
runs a small state machine: approach above the grasp point at a travel height that clears the scene, descend,
close, lift (re-grasp if the object did not come up), carry, lower, open, retreat. Position is servoed with a
proportional + integral law on the OSC delta-pose action; orientation holds the episode's start orientation, turned
in yaw so the fingers close across the object's narrow side. Bowls are grasped on the rim, one finger inside.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vlactl.expert.geometry import clearance, object_body, obstacle_boxes, object_shape

POS_SCALE = 0.05  # metres per unit of action (robosuite OSC_POSE output_max)
ROT_SCALE = 0.5  # radians per unit of action
OPEN, CLOSE = -1.0, 1.0


@dataclass(frozen=True)
class ExpertConfig:
    kp: float = 1.0 / 0.05 * 0.7  # action per metre of error: ~70% of the error per step
    ki: float = 2.0
    kr: float = 1.5  # rotation action per radian of error / ROT_SCALE
    travel_clearance: float = 0.12  # above the top of the highest relevant object
    max_travel_z: float = 1.2  # the Panda cannot reach much higher over the far side of the table
    tolerance: float = 0.01
    final_approach: float = 0.03  # the last 3 cm of the descent are slower, so a close a step early or late lands
    final_speed: float = 0.3  # nearer the grasp point: 4-5 mm a step, was 5-8 mm (action units; 1.0 moves ~12 mm)
    close_steps: int = 10
    preclose_steps: int = 3  # gripper commands of +1 before a rim grasp: the fingers end about half open
    open_steps: int = 8
    lift_check: float = 0.04  # the object must rise this much, else re-grasp
    max_regrasps: int = 3
    rim_inset: float = 0.005  # grip site this far inside the rim's outer edge: the fingers straddle the wall evenly
    comfortable_reach: float = 0.72  # horizontal distance from the robot base beyond which grasps are penalised
    reach_weight: float = 0.5  # score per metre beyond it (clearance scores saturate at 0.05)
    rim_depth: float = 0.02  # grip site below a bowl's rim top; deeper and the inner finger meets the sloped wall
    regrasp_rim_depth: float = 0.03  # after a grip that did not lift the bowl (e.g. pinched on a drawer's wall): deeper
    empty_aperture: float = 0.04  # fingers closed further than this while lifting hold nothing (a bowl on the
                                  # ramekin is held at 0.05, one on the table at 0.1): re-grasp at once
    miss_first_grasp: bool = False  # recovery demonstrations: the first grasp closes above the rim, on nothing
    miss_height: float = 0.03  # that grasp's height above the rim top: clear of it, so the bowl is not moved
    closed_approach: bool = False  # approach with the gripper closed, open fully over the grasp point, then descend


def _quat_mul(a, b):
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array([
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    ])


def _quat_conj(q):
    return np.array([-q[0], -q[1], -q[2], q[3]])


def _quat_to_axis_angle(q):
    q = q if q[3] >= 0 else -q
    s = np.linalg.norm(q[:3])
    if s < 1e-9:
        return np.zeros(3)
    return q[:3] / s * 2 * np.arctan2(s, q[3])


def _yaw_quat(yaw):
    return np.array([0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)])


def _yaw_of(xmat) -> float:
    return float(np.arctan2(xmat[1, 0], xmat[0, 0]))


class ScriptedExpert:
    """Call `reset(env, obs)` at the start of an episode, then `act(obs)` every step."""

    def __init__(self, cfg: ExpertConfig = ExpertConfig()):
        self.cfg = cfg

    # --- episode set-up -------------------------------------------------------------------------------------
    def reset(self, env, obs) -> None:
        predicate, target, destination = env.goal[0][:3]
        self.target = target
        self.destination = destination.replace("_contain_region", "")
        sim = env.env.sim
        self.sim = sim
        self.shape = object_shape(sim.model, sim.data, self.target)
        self.dest_shape = object_shape(sim.model, sim.data, self.destination)
        self.is_bowl = "bowl" in target
        self.start_quat = np.asarray(obs.raw["robot0_eef_quat"], dtype=np.float64)
        self.base = np.array(sim.data.body_xpos[sim.model.body_name2id("robot0_base")])
        self.obstacles = obstacle_boxes(sim.model, sim.data, [object_body(sim.model, self.target)])
        self.phase, self.timer, self.regrasps, self.failed = "approach", 0, 0, []
        self.missing = self.cfg.miss_first_grasp
        self.closed_approach = self.cfg.closed_approach
        self.integral = np.zeros(3)
        self._plan_grasp(obs)

    def _body(self, name):
        return object_body(self.sim.model, name)

    def _pose(self, name):
        b = self._body(name)
        return np.array(self.sim.data.xpos[b]), np.array(self.sim.data.xmat[b]).reshape(3, 3)

    def _plan_grasp(self, obs) -> None:
        """Choose the grasp point and gripper yaw from the object's current pose, away from obstacles."""
        pos, rot = self._pose(self.target)
        half = self.shape.half_extent
        centre = pos + rot @ self.shape.center
        top = pos[2] + rot[2] @ np.where(rot[2] >= 0, self.shape.hi, self.shape.lo)
        bottom = pos[2] + rot[2] @ np.where(rot[2] >= 0, self.shape.lo, self.shape.hi)
        if self.is_bowl:
            # Rim grasp with one finger inside the bowl: the finger axis must be radial. Four rim points are
            # possible (two yaws x two sides); take the one whose hand column is furthest from any obstacle.
            z = top - (self.cfg.regrasp_rim_depth if self.failed else self.cfg.rim_depth)
            if self.missing:
                z = top + self.cfg.miss_height
            candidates = []
            for yaw in (0.0, np.pi / 2):
                axis = np.array([-np.sin(yaw), np.cos(yaw), 0.0])  # finger axis: world y at yaw 0
                for side in (-1.0, 1.0):
                    offset = side * (half[0] - self.cfg.rim_inset) * axis
                    candidates.append((yaw, offset, np.array([centre[0], centre[1], z]) + offset))
        else:
            # Close across the narrow horizontal side: align the finger axis (world y at yaw 0) with it.
            narrow_axis = rot[:, 0] if half[0] < half[1] else rot[:, 1]
            yaw = float(np.arctan2(narrow_axis[1], narrow_axis[0])) - np.pi / 2
            yaw = (yaw + np.pi / 2) % np.pi - np.pi / 2  # the gripper is symmetric: turn at most 90 deg
            depth = min(0.03, 0.8 * (top - bottom))
            candidates = [(yaw, np.zeros(3), np.array([centre[0], centre[1], top - depth]))]
        # A grasp that already failed goes to the back of the queue: re-grasps try the next-best rim point.
        # Points beyond the arm's comfortable reach lose too: the Panda cannot get over the table's far edge.
        scores = [self._hand_clearance(point, yaw) - self._reach_penalty(point) - self.failed.count(i)
                  for i, (yaw, _, point) in enumerate(candidates)]
        self.candidate = int(np.argmax(scores))
        self.grasp_yaw, self.grasp_offset, self.grasp_point = candidates[self.candidate]
        self.grasp_height_above_obj = self.grasp_point[2] - pos[2]
        self.obj_start_z = pos[2]

    def _reach_penalty(self, point: np.ndarray) -> float:
        reach = np.linalg.norm(point[:2] - self.base[:2])
        return self.cfg.reach_weight * max(0.0, reach - self.cfg.comfortable_reach)

    def _hand_clearance(self, grasp_point: np.ndarray, yaw: float) -> float:
        """How far the gripper stays from obstacles while descending onto `grasp_point` (soft score, higher is better).

        Sampled as two boxes: the (half-closed) fingers near the grasp point, and the wide hand above them.
        """
        c, s = np.cos(yaw), np.sin(yaw)
        finger_axis, across = np.array([-s, c, 0.0]), np.array([c, s, 0.0])

        def box(u_half, v_half, w_lo, w_hi):
            u, v, w = (g.ravel() for g in np.meshgrid(
                np.linspace(-u_half, u_half, 7), np.linspace(-v_half, v_half, 3), np.linspace(w_lo, w_hi, 5)))
            return grasp_point + u[:, None] * finger_axis + v[:, None] * across + w[:, None] * np.array([0, 0, 1.0])

        points = np.concatenate([box(0.03, 0.012, -0.02, 0.05), box(0.1, 0.03, 0.07, 0.16)])
        return clearance(points, self.obstacles)

    def _travel_z(self) -> float:
        dest_pos, dest_rot = self._pose(self.destination)
        dest_top = dest_pos[2] + self.dest_shape.hi[2]
        tallest = max(dest_top, self.obj_start_z + 2 * self.shape.half_extent[2])
        return min(tallest + self.cfg.travel_clearance + self.shape.half_extent[2], self.cfg.max_travel_z)

    def _place_point(self) -> np.ndarray:
        dest_pos, dest_rot = self._pose(self.destination)
        centre = dest_pos + dest_rot @ self.dest_shape.center
        surface = dest_pos[2] + (self.dest_shape.lo[2] + 0.02 if "basket" in self.destination else self.dest_shape.hi[2])
        obj_bottom_to_grip = self.grasp_height_above_obj - self.shape.lo[2]
        return np.array([centre[0] + self.grasp_offset[0], centre[1] + self.grasp_offset[1], surface + obj_bottom_to_grip + 0.02])

    # --- control -------------------------------------------------------------------------------------------
    def _servo(self, eef, target, grip, yaw) -> np.ndarray:
        err = target - eef
        self.integral = np.clip(self.integral + err, -0.05, 0.05)
        dpos = np.clip(self.cfg.kp * err + self.cfg.ki * self.integral, -1.0, 1.0)
        q_target = _quat_mul(_yaw_quat(yaw), self.start_quat)
        rot_err = _quat_to_axis_angle(_quat_mul(q_target, _quat_conj(self.eef_quat)))
        drot = np.clip(self.cfg.kr * rot_err / ROT_SCALE, -1.0, 1.0)
        return np.concatenate([dpos, drot, [grip]])

    def _go(self, phase):
        self.phase, self.timer = phase, 0
        self.integral[:] = 0

    def act(self, obs) -> np.ndarray:
        eef = np.asarray(obs.raw["robot0_eef_pos"], dtype=np.float64)
        self.eef_quat = np.asarray(obs.raw["robot0_eef_quat"], dtype=np.float64)
        self.timer += 1
        cfg = self.cfg
        obj_pos, _ = self._pose(self.target)
        travel = self._travel_z()
        close = lambda p: np.linalg.norm(p - eef) < cfg.tolerance  # noqa: E731

        if self.phase == "approach":
            remaining = np.linalg.norm(self.grasp_point[:2] - eef[:2])
            # Near the object, come down: the far side of the table is out of reach at full travel height.
            hover = travel if remaining > 0.1 else min(travel, self.grasp_point[2] + 0.1)
            above = np.array([*self.grasp_point[:2], hover])
            if eef[2] < hover - 0.03 and remaining > 0.02:
                above = np.array([eef[0], eef[1], hover])  # rise first, then move across
            # Already over the grasp point (a re-grasp after a miss): straight down.
            if (remaining < 0.01 and (eef[2] >= hover - 0.03 or eef[2] > self.grasp_point[2])) or self.timer > 60:
                # a closed approach opens first (regrasp_open), then comes back here already over the grasp point
                self._go("regrasp_open" if self.closed_approach else "descend")
                self.closed_approach = False
            return self._servo(eef, above, CLOSE if self.closed_approach else OPEN, self.grasp_yaw)
        if self.phase == "descend":
            remaining = np.linalg.norm(self.grasp_point - eef)
            if remaining < cfg.tolerance or self.timer > 40:
                self._go("close")
            # Bowls: close the fingers part-way, then hold (action 0), so they fit between the rim and nearby walls.
            grip = (CLOSE if self.timer <= cfg.preclose_steps else 0.0) if self.is_bowl else OPEN
            action = self._servo(eef, self.grasp_point, grip, self.grasp_yaw)
            if remaining < cfg.final_approach:
                action[:3] *= min(1.0, cfg.final_speed / max(np.linalg.norm(action[:3]), 1e-9))
            return action
        if self.phase == "close":
            if self.timer >= cfg.close_steps:
                self.lift_start_z = eef[2]
                self._go("lift")
            return self._servo(eef, self.grasp_point, CLOSE, self.grasp_yaw)
        if self.phase == "lift":
            target = np.array([eef[0], eef[1], travel])
            # Held if the object rises with the hand; relative, because over the tall cabinet the arm is near the top
            # of its reach and cannot lift far.
            hand_rise, obj_rise = eef[2] - self.lift_start_z, obj_pos[2] - self.obj_start_z
            empty = self.timer > 2 and obs.state[6] < cfg.empty_aperture
            if obj_rise > cfg.lift_check or (hand_rise > 0.025 and obj_rise > 0.7 * hand_rise):
                self._go("carry")
            elif self.missing and (empty or self.timer > 25):  # the deliberate miss: same grasp, now done right
                self.missing = False
                self._plan_grasp(obs)
                self._go("regrasp_open")
            elif empty or self.timer > 25:
                if self.regrasps < cfg.max_regrasps:
                    self.regrasps += 1
                    self.failed.append(self.candidate)
                    self._plan_grasp(obs)
                    self._go("regrasp_open")
                else:
                    self._go("carry")
            return self._servo(eef, target, CLOSE, self.grasp_yaw)
        if self.phase == "regrasp_open":
            # Fully open before the next descent: its part-way pre-close is timed from open fingers.
            if self.timer >= cfg.open_steps and (obs.state[6] > 0.9 or self.timer > 20):
                self._go("approach")
            return self._servo(eef, eef, OPEN, self.grasp_yaw)
        if self.phase == "carry":
            place = self._place_point()
            remaining = np.linalg.norm(place[:2] - eef[:2])
            # Near the destination, come down: the far side of the table is out of reach at full travel height.
            above = np.array([place[0], place[1], travel if remaining > 0.1 else min(travel, place[2] + 0.12)])
            if remaining < 0.01 or self.timer > 80:
                self._go("lower")
            if eef[2] < travel - 0.03 and np.linalg.norm(above[:2] - eef[:2]) > 0.05:
                above = np.array([eef[0], eef[1], travel])  # rise before moving across
            return self._servo(eef, above, CLOSE, self.grasp_yaw)
        if self.phase == "lower":
            place = self._place_point()
            if close(place) or self.timer > 40:
                self._go("release")
            return self._servo(eef, place, CLOSE, self.grasp_yaw)
        if self.phase == "release":
            if self.timer >= cfg.open_steps:
                self._go("retreat")
            return self._servo(eef, eef, OPEN, self.grasp_yaw)
        # retreat: rise and wait; LIBERO's success check ends the episode
        return self._servo(eef, np.array([eef[0], eef[1], travel]), OPEN, self.grasp_yaw)
