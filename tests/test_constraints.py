"""Constraint parsing, judging, boxes, filters and prompts, one constraint or several (pure functions)."""

import math

import numpy as np

import pandas as pd
import pytest

from vlactl.errors import UsageError
from vlactl.rollout.constraints import (KINDS, Bounds, Constraint, action_bound, box, constraint_name, filter_actions,
                                       held_by_default, judge_all, judge_steps, parse_constraint, parse_constraints,
                                       prompted, start_gripper)


def test_parse_defaults_and_none():
    assert parse_constraint("none") is None
    c = parse_constraint("speed=high")
    assert (c.feature, c.value, c.window, c.probe_feature, c.upper) == ("speed", "high", 25, "speed", True)
    assert parse_constraint("gripper=open", window=5).window == 5
    assert {parse_constraint(f"{f}={v}").window for f, (vs, *_) in KINDS.items() for v in vs} == {15, 25}


@pytest.mark.parametrize("text", ["gripper=wide", "color=red", "gripper", "height=LOW"])
def test_bad_constraints_name_what_is_allowed(text):
    with pytest.raises(UsageError, match=r"allowed: none, gripper=open\|closed, height=low\|high, speed=low\|high"):
        parse_constraint(text)


def steps(**columns):
    n = len(next(iter(columns.values())))
    return pd.DataFrame({"t": range(n), "z": 1.0, "gripper_action": -1.0, "speed": 0.0, **columns})


@pytest.mark.parametrize("text, columns, expected", [
    ("gripper=open", {"gripper_action": [-1, -1, 1, 1]}, [True, True, False, None]),
    ("gripper=closed", {"gripper_action": [-1, -1, 1, 1]}, [False, False, True, None]),
    ("height=low", {"z": [0.9, 0.95, 0.91, 2.0]}, [True, False, True, None]),  # start height 0.92
    ("height=high", {"z": [0.9, 0.95, 0.91, 0.0]}, [False, True, False, None]),
    ("speed=low", {"speed": [0.05, 0.2, 0.1, 9.0]}, [True, False, True, None]),  # threshold 0.1
])
def test_steps_are_judged_inside_the_window_only(text, columns, expected):
    judged, satisfaction = judge_steps(parse_constraint(text, window=3), steps(**columns), 0.92, 0.1)
    assert judged["in_window"].tolist() == [True, True, True, False]
    assert [None if v is pd.NA else bool(v) for v in judged["satisfied"]] == expected
    assert satisfaction == pytest.approx(sum(bool(v) for v in expected[:3]) / 3)


def test_boxes_point_the_right_way():
    assert box(parse_constraint("gripper=open"), 0.0) == (-math.inf, -2.0)  # the logit of 'close' kept low
    assert box(parse_constraint("gripper=closed"), 0.0, logit_margin=3.0) == (3.0, math.inf)
    assert box(parse_constraint("height=low"), 0.95) == (-math.inf, 0.95)
    assert box(parse_constraint("speed=high"), 0.1) == (0.1, math.inf)


def test_prompt_appends_the_constraint():
    text = prompted("pick up the bowl", parse_constraint("gripper=closed"))
    assert text == "pick up the bowl and keep the gripper closed"


@pytest.mark.parametrize("setting, constraint, method, expected", [
    ("auto", "gripper=closed", "none", "closed"),  # the paper's favourable start for its baselines
    ("auto", "gripper=closed", "prompt", "closed"),
    ("auto", "gripper=closed", "control", "open"),  # the controller has to close it
    ("auto", "gripper=open", "none", "open"),
    ("auto", "height=low", "none", "open"),
    ("auto", "none", "none", "open"),
    ("closed", "height=low", "control", "closed"),  # asked for: taken as is
])
def test_start_gripper_follows_the_paper_for_its_baselines(setting, constraint, method, expected):
    assert start_gripper(setting, parse_constraint(constraint), method) == expected


# --- several constraints at once ---------------------------------------------------------------------------------

@pytest.mark.parametrize("text", ["[height=high,speed=low]", "height=high,speed=low", "[speed=low, height=high]",
                                  ["speed=low", "height=high"]])
def test_several_constraints_parse_to_one_canonical_list(text):
    constraints = parse_constraints(text, window=7)
    assert constraint_name(constraints) == "height=high,speed=low"  # KINDS order, whatever the order typed
    assert [c.window for c in constraints] == [7, 7]
    assert [c.window for c in parse_constraints(text)] == [15, 25]  # each its own default window
    assert parse_constraints("none") == () and constraint_name(()) == "none"
    assert parse_constraints("gripper=open") == (parse_constraint("gripper=open"),)
    assert parse_constraints("[gripper=open]") == (parse_constraint("gripper=open"),)


@pytest.mark.parametrize("text, message", [
    ("[height=high,speed=slow]", r"unknown constraint 'speed=slow' in constraint=\[height=high,speed=slow\]; "
                                 r"allowed: gripper=open\|closed, height=low\|high, speed=low\|high"),
    ("height=high,colour=red", "unknown constraint 'colour=red'"),
    ("[height=low,height=high]", r"two constraints on height \(height=low, height=high\); one per feature"),
    ("[speed=low,speed=low]", "two constraints on speed"),
    ("[]", r"names no constraint; give one or more of gripper=open\|closed"),
    ("[height=high,none]", "'none' cannot be in a list"),
    ("[height=high,,speed=low]", "'an empty entry' cannot be in a list"),
    ("[height=high", "unbalanced brackets"),
])
def test_bad_constraint_lists_are_one_line_usage_errors(text, message):
    with pytest.raises(UsageError, match=message) as error:
        parse_constraints(text)
    assert "\n" not in str(error.value)


def test_several_constraints_hold_what_every_one_holds_and_none_steers():
    assert held_by_default(parse_constraints("[height=high,speed=low]")) == ("gripper_action",)
    assert held_by_default(parse_constraints("[gripper=open,height=low]")) == ("dx", "dy")
    assert held_by_default(parse_constraints("[gripper=open,speed=low]")) == ()
    for feature, (values, *_, holds) in KINDS.items():  # one constraint: its own holds, as before
        assert held_by_default(parse_constraint(f"{feature}={values[0]}")) == holds


def test_several_constraints_are_judged_each_in_its_own_window():
    constraints = (Constraint("height", "high", 2), Constraint("speed", "low", 4))
    table = steps(z=[0.93, 0.91, 0.91, 0.95, 0.95], speed=[0.05, 0.05, 0.2, 0.05, 0.2])  # start 0.92, threshold 0.1
    judged, satisfaction, own = judge_all(constraints, table, 0.92, 0.1)
    assert judged["in_window_height"].tolist() == [True, True, False, False, False]
    assert judged["in_window"].tolist() == [True, True, True, True, False]
    assert [None if v is pd.NA else bool(v) for v in judged["satisfied_height"]] == [True, False, None, None, None]
    assert [None if v is pd.NA else bool(v) for v in judged["satisfied"]] == [True, False, False, True, None]
    assert satisfaction == pytest.approx(2 / 4) and own == {"height": 0.5, "speed": pytest.approx(3 / 4)}
    assert "constraint_value" not in judged and "constraint_value_speed" in judged
    one, alone = judge_steps(constraints[0], table, 0.92, 0.1)
    assert judge_all(constraints[:1], table, 0.92, 0.1)[1] == alone and "satisfied_height" not in one


def test_filter_of_height_and_speed_satisfies_both_where_it_can():
    high, low = parse_constraints("[height=high,speed=low]")
    z, z0, threshold = 0.995, 1.0, 0.1  # below the start height: the barrier asks for a rise
    bounds = Bounds(speed_threshold=threshold, metres_per_unit=0.01)
    lo = action_bound(high, z, z0, bounds)[0]
    fast = action_bound(low, z, threshold, bounds)[1]
    assert lo == pytest.approx(0.25) and fast == pytest.approx(0.45)  # 10% inside the threshold
    a = np.array([0.6, 0.0, -0.5, 0.1, 0.0, 0.0, -1.0])  # too fast and going down
    out = filter_actions((high, low), a, z, z0, bounds)
    assert out[2] >= lo - 1e-9 and np.linalg.norm(out[:3]) <= fast + 1e-9 and np.array_equal(out[3:], a[3:])
    assert out[2] == pytest.approx(lo) and np.linalg.norm(out[:3]) == pytest.approx(fast)  # both bounds bind
    assert out[1] == 0.0 and out[0] == pytest.approx(np.sqrt(fast ** 2 - lo ** 2))  # x kept as much as it can be
    fine = np.array([0.1, 0.1, 0.3, 0.0, 0.0, 0.0, 1.0])
    assert np.array_equal(filter_actions((high, low), fine, z, z0, bounds), fine)  # nothing to change
    slow = Bounds(speed_threshold=0.02, metres_per_unit=0.01)
    out = filter_actions((high, low), a, 0.98, z0, slow)  # needs dz >= 1 at speed <= 0.1: infeasible
    assert out[2] == pytest.approx(action_bound(high, 0.98, z0, slow)[0]) and out[:2].tolist() == [0.0, 0.0]
    gripper, height = parse_constraints("[gripper=closed,height=high]")
    out = filter_actions((gripper, height), a, z, z0, bounds)
    assert out[6] == 1.0 and out[2] == pytest.approx(lo)


def test_several_constraints_are_said_in_the_prompt_and_favour_the_gripper_start():
    both = parse_constraints("[gripper=closed,height=low]")
    assert prompted("pick up the bowl", both) == "pick up the bowl and keep the gripper closed and stay low"
    assert start_gripper("auto", both, "prompt") == "closed" and start_gripper("auto", both, "control") == "open"
    assert start_gripper("auto", parse_constraints("[height=low,speed=low]"), "none") == "open"
