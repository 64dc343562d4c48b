"""Perturbations of the arm (vlactl/env/perturbations.py) and the action-space safety filter (method=filter)."""

from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
from omegaconf import OmegaConf
from scipy.spatial.transform import Rotation

from vlactl.config import CONF_DIR
from vlactl.env.perturbations import (TILT_SIZE, Perturbation, parse_perturbation, parse_tilt_size,
                                       random_perturbation)
from vlactl.errors import UsageError
from vlactl.rollout.constraints import (Bounds, action_bound, action_quantity, filter_action, parse_constraint,
                                       parse_constraints)
from vlactl.rollout.runner import rollout_config, run_rollout

CM = Bounds(speed_threshold=0.2, metres_per_unit=0.01)  # 1 cm a unit of command, the barrier closing half a step
CM_ABOVE = replace(CM, height_margin=0.01)  # its level 1 cm inside the allowed side


class Obs:
    def __init__(self, pos):
        self.state = np.array([*pos, 0, 0, 0, 1.0])


def test_raise_drives_the_hand_up_from_where_the_stretch_began_then_hands_back():
    hook = Perturbation("raise", start=2, steps=3, size=0.08).hook()
    policy = np.array([0.5, -0.5, -1.0, 0.1, 0.1, 0.1, -1.0])
    assert np.array_equal(hook(1, Obs([0, 0, 1.0]), policy), policy)  # before the stretch: the policy's action
    first = hook(2, Obs([0, 0, 1.0]), policy)
    assert first[2] == 1.0 and first[0] == first[1] == 0 and not first[3:6].any() and first[6] == -1.0
    near = hook(3, Obs([0, 0, 1.07]), policy)  # 1 cm below the target (anchored at step 2's z, not this one's)
    assert near[2] == pytest.approx(14.0 * 0.01)
    assert np.array_equal(hook(5, Obs([0, 0, 1.08]), policy), policy)  # handed back


@pytest.mark.parametrize("kind, check", [
    ("slow", lambda a: np.allclose(a[:6], np.full(6, 0.6) / 3) and a[6] == -1),
    ("close", lambda a: np.allclose(a[:6], 0.6) and a[6] == 1.0),
    ("hold", lambda a: not a[:6].any()),
    ("shift", lambda a: a[1] == pytest.approx(14.0 * 0.05) and a[0] == a[2] == 0),
    ("tilt", lambda a: a[3] == pytest.approx(3.0 * 0.07) and not a[[0, 1, 2, 4, 5]].any()),
])
def test_each_kind_changes_what_it_says(kind, check):
    action = np.array([0.6] * 6 + [-1.0])
    assert check(Perturbation(kind).hook()(0, Obs([0.1, 0.2, 1.0]), action))


@pytest.mark.parametrize("args, message", [
    (("lift",), "unknown perturbation 'lift'; allowed: none, raise"),
    (("raise", 0, 15, 0.5), r"perturb_size=0.5 out of range for perturb=raise: metres up in \(0, 0.2\]"),
    (("hold", 0, 15, 0.1), "perturb=hold takes no size"),
    (("slow", 0, 0), "perturb_steps must be in 1..220"),
    (("slow", -1), "perturb_start must be >= 0"),
    (("slow", 300), "past the episode's 220 steps"),
])
def test_bad_perturbations_are_one_line_usage_errors(args, message):
    with pytest.raises(UsageError, match=message):
        parse_perturbation(*args, max_steps=220)


def test_tilt_turns_the_hand_about_world_x_from_any_heading_and_stops_there():
    hook = Perturbation("tilt", size=0.1).hook()
    start = Obs([0, 0, 1.0])
    start.state[3:6] = [np.pi, 0.0, 0.5]  # the gripper pointing down, turned 0.5 rad about z
    first = hook(0, start, np.zeros(7))
    assert first[3] == pytest.approx(0.3) and first[4:6] == pytest.approx([0, 0], abs=1e-9)
    there = Obs([0, 0, 1.0])
    turned = Rotation.from_rotvec([0.1, 0, 0]) * Rotation.from_euler("xyz", start.state[3:6])
    there.state[3:6] = turned.as_euler("xyz")
    assert hook(1, there, np.zeros(7))[3:6] == pytest.approx([0, 0, 0], abs=1e-9)


def test_demonstration_perturbations_cover_every_kind_reproducibly():
    kinds = {random_perturbation(np.random.default_rng(k), k).kind for k in range(5)}
    assert kinds == {"raise", "hold", "shift", "slow", "close"}
    assert random_perturbation(np.random.default_rng(3), 3) == random_perturbation(np.random.default_rng(3), 3)
    tilts = [random_perturbation(np.random.default_rng(k), k, ("tilt",)) for k in range(20)]
    assert {p.kind for p in tilts} == {"tilt"} and all(0.03 <= abs(p.size) <= 0.15 for p in tilts)
    assert min(p.size for p in tilts) < 0 < max(p.size for p in tilts)  # turned either way
    small = [random_perturbation(np.random.default_rng(k), k, ("tilt",), (0.01, 0.04)) for k in range(20)]
    assert all(0.01 <= abs(p.size) <= 0.04 for p in small)


def test_demos_default_tilts_are_the_ones_random_perturbation_draws():
    assert tuple(OmegaConf.load(CONF_DIR / "demos.yaml").tilt_size) == TILT_SIZE


@pytest.mark.parametrize("value, message", [([0.04, 0.01], r"tilt_size=\[0.04,0.01\] out of range"),
                                            ([0.0, 0.1], "out of range"), ([0.1, 0.6], "<= 0.5"),
                                            ("small", "must be \\[low,high\\], got 'small'")])
def test_tilt_sizes_out_of_range_are_refused_by_name(value, message):
    with pytest.raises(UsageError, match=message):
        parse_tilt_size(value)


def test_height_barrier_lets_the_hand_approach_the_start_height_by_the_decay_rate():
    high, low = parse_constraint("height=high"), parse_constraint("height=low")
    assert action_bound(high, 1.02, 1.0, CM) == (pytest.approx(-1.0), np.inf)  # may close half of 2 cm
    assert action_bound(low, 0.98, 1.0, CM)[1] == pytest.approx(1.0)
    assert action_bound(high, 0.99, 1.0, CM)[0] == pytest.approx(0.5)  # below the bound: must move back up
    a = np.array([0.3, 0.2, -0.9, 0, 0, 0, -1.0])
    out = filter_action(high, a, 1.01, 1.0, CM)
    assert out[2] == pytest.approx(-0.5) and np.array_equal(np.delete(out, 2), np.delete(a, 2))
    assert np.array_equal(filter_action(high, a * [1, 1, -1, 1, 1, 1, 1], 1.02, 1.0, CM), a * [1, 1, -1, 1, 1, 1, 1])


@pytest.mark.parametrize("value", ["high", "low"])
def test_height_quantity_keeps_the_barrier_at_every_step_of_the_chunk(value):
    """box=action: a chunk is inside its height bound exactly when the hand, moved s per unit of dz each step, keeps
    h_j >= (1 - decay)^j h_0 at every step j of it, not only on average (a mean can hide an early dip)."""
    constraint, rng = parse_constraint(f"height={value}"), np.random.default_rng(0)
    sign, s, z0, decay = (1 if value == "high" else -1), 0.0127, 1.0, 0.5
    agree = 0
    for _ in range(400):
        z = z0 + sign * rng.uniform(-0.01, 0.05)
        chunk = np.zeros((5, 7))
        chunk[:, 2] = rng.normal(0.0, 1.0, 5)
        lo, hi = action_bound(constraint, z, z0, Bounds(metres_per_unit=s, decay=decay), steps=5)
        q = action_quantity(constraint, chunk, decay)
        heights = sign * (z + s * np.cumsum(chunk[:, 2]) - z0)
        kept = bool(np.all(heights >= (1 - decay) ** np.arange(1, 6) * sign * (z - z0) - 1e-12))
        agree += (lo <= q <= hi) == kept
    assert agree == 400
    early_dip = np.zeros((5, 7))
    early_dip[:, 2] = [-2.0, 0.5, 0.5, 0.5, 0.5] if value == "high" else [2.0, -0.5, -0.5, -0.5, -0.5]
    lo, hi = action_bound(constraint, z0 + sign * 0.02, z0, Bounds(metres_per_unit=s, decay=decay), steps=5)
    assert lo <= early_dip[:, 2].mean() <= hi and not lo <= action_quantity(constraint, early_dip, decay) <= hi


def test_speed_filter_scales_the_translation_along_its_direction():
    low, high = parse_constraint("speed=low"), parse_constraint("speed=high")
    a = np.array([0.6, 0.8, 0.0, 0.1, 0, 0, 1.0])  # norm 1.0 -> 0.01 m a step = 0.2 m/s at 20 Hz
    slowed = filter_action(low, a, 1.0, 0.1, CM)
    # 0.1 m/s is 0.5 units; the bound lies speed_margin (0.1) inside it: 0.45 slow, 0.55 fast
    assert np.linalg.norm(slowed[:3]) == pytest.approx(0.45) and np.allclose(slowed[:3] / 0.45, a[:3])
    assert np.array_equal(filter_action(high, a, 1.0, 0.1, CM), a)
    assert np.linalg.norm(filter_action(high, a * 0.1, 1.0, 0.1, CM)[:3]) == pytest.approx(0.55)
    # speed_margin moves the bound further inside: 0.5 units x (1 -+ 0.3)
    assert np.linalg.norm(filter_action(low, a, 1.0, 0.1, replace(CM, speed_margin=0.3))[:3]) == pytest.approx(0.35)
    assert action_bound(high, 1.0, 0.1, replace(CM, speed_margin=0.3)) == (pytest.approx(0.65), np.inf)


def test_gripper_filter_forces_the_command():
    a = np.zeros(7)
    assert filter_action(parse_constraint("gripper=closed"), a, 1.0, 0.0, CM)[6] == 1.0
    assert filter_action(parse_constraint("gripper=open"), a, 1.0, 0.0, CM)[6] == -1.0


def run(root, *extra):
    return run_rollout(rollout_config(["model=random", "tasks=[0]", "episodes_per_task=1", "max_steps=6", "workers=1",
                                       f"output_root={root}", *extra]))


def test_filter_satisfies_gripper_closed_in_every_window_step(tmp_path):
    summary = run(tmp_path, "constraint=gripper=closed", "method=filter", "window=4", "metres_per_unit=0.012")
    steps = pd.read_parquet(tmp_path / "random_libero_spatial_gripper-closed_filter" / "steps.parquet")
    assert (steps[steps["in_window"]]["gripper_action"] == 1.0).all()
    assert summary["satisfaction"] == 1.0 and summary["method"] == "filter"


def test_perturbed_rollout_raises_the_hand_and_records_the_perturbation(tmp_path):
    summary = run(tmp_path, "perturb=raise", "perturb_steps=4", "perturb_size=0.05")
    out = tmp_path / "random_libero_spatial_perturb-raise"
    steps, episodes = pd.read_parquet(out / "steps.parquet"), pd.read_parquet(out / "episodes.parquet")
    assert (steps["dz"].iloc[:2] > 0.5).all()  # driven up at first, whatever the random policy says
    assert steps["z"].iloc[4] - steps["z"].iloc[0] > 0.02
    assert episodes["perturbation"].tolist() == ["raise:0.05@0+4"] and summary["perturbation"] == "raise:0.05@0+4"


@pytest.mark.parametrize("extra, message", [
    (["method=filter"], "method=filter needs a constraint"),
    (["perturb=wobble"], "unknown perturbation 'wobble'"),
    (["perturb=raise", "perturb_size=1.0"], "perturb_size=1.0 out of range"),
    (["constraint=height=high", "method=filter", "barrier_decay=0"], "barrier_decay must be in"),
])
def test_bad_filter_or_perturbation_settings_fail_before_any_worker(tmp_path, extra, message):
    with pytest.raises(UsageError, match=message):
        run(tmp_path, *extra)
    assert not any(tmp_path.iterdir())


def test_height_margin_moves_the_barrier_inside_the_allowed_side():
    high, low = parse_constraint("height=high"), parse_constraint("height=low")
    assert action_bound(high, 1.0, 1.0, CM_ABOVE)[0] == pytest.approx(0.5)  # at z0: must rise
    assert action_bound(low, 1.0, 1.0, CM_ABOVE)[1] == pytest.approx(-0.5)  # at z0: must sink
    assert action_bound(high, 1.03, 1.0, CM_ABOVE)[0] == pytest.approx(-1.0)


def test_pause_stops_the_arm_only_where_a_pausable_constraint_binds():
    from vlactl.rollout.constraints import filter_actions

    high, low = parse_constraint("height=high"), parse_constraint("speed=low")
    down = np.array([0.5, -0.4, -1.0, 0.1, 0.2, 0.0, -1.0])  # on its way across and down: breaks the barrier
    paused = filter_actions([high], down, 1.0, 1.0, CM_ABOVE, pause=True)
    assert np.allclose(paused[[0, 1, 3, 4, 5]], 0.0) and paused[6] == -1.0
    assert paused[2] == pytest.approx(action_bound(high, 1.0, 1.0, CM_ABOVE)[0])  # the rise it asks
    above = filter_actions([high], down, 1.015, 1.0, CM_ABOVE, pause=True)
    assert np.allclose(above[:6], 0.0)  # above the level nothing need rise: a full stop
    across = np.array([0.5, -0.4, 0.2, 0.0, 0.0, 0.0, 1.0])  # keeps the barrier: untouched
    assert np.array_equal(filter_actions([high], across, 1.0, 1.0, CM, pause=True), across)
    fast = filter_actions([low], down, 1.0, 1.0, CM, pause=True)
    assert np.allclose(fast[:6], 0.0)  # speed=low: stopped, not scaled
    closed = filter_actions(parse_constraints("gripper=closed,height=high"), down, 1.0, 1.0, CM, pause=True)
    assert np.allclose(closed[[0, 1]], 0.0) and closed[6] == 1.0  # the gripper still forced


@pytest.mark.parametrize("extra, message", [
    (["constraint=height=high", "method=prompt"], "pause=true needs method=filter or method=control with box=action, "
                                                   "not method=prompt"),
    (["constraint=height=high", "method=control", "box=state"], "not method=control with box=state"),
    (["constraint=gripper=open", "method=filter"], "no constraint in constraint=gripper=open asks for"),
    (["constraint=[height=high,speed=high]", "method=filter"], "cannot go with speed=high"),
])
def test_bad_pause_settings_fail_before_any_worker(tmp_path, extra, message):
    with pytest.raises(UsageError, match=message):
        run(tmp_path, "pause=true", "metres_per_unit=0.012", "speed_threshold=0.2", *extra)
    assert not any(tmp_path.iterdir())


def test_filter_pause_keeps_the_hand_still_and_up_through_the_window(tmp_path):
    # the pause acts only where a prediction breaks a bound: a speed bound no motion keeps makes it act at every
    # window step, whatever the random fixture predicts (alone, height=high binds only on a descending prediction)
    run(tmp_path, "constraint=[height=high,speed=low]", "method=filter", "pause=true", "window=4",
        "metres_per_unit=0.012", "speed_threshold=0.001")
    [out] = tmp_path.iterdir()
    assert out.name.endswith("_filter-pause")  # never the smallest-change filter's folder
    steps = pd.read_parquet(out / "steps.parquet")
    window = steps[steps["in_window"]]
    assert (window["z"] >= window["z"].iloc[0] - 1e-3).all()
    assert np.ptp(window[["x", "y"]].to_numpy(), axis=0).max() < 0.01  # it does not move on across
    assert (window[["droll", "dpitch", "dyaw"]] == 0).all().all()  # a stop, not the speed scaled down
    assert pd.read_parquet(out / "episodes.parquet")["method"].tolist() == ["filter+pause"]
