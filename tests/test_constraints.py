"""Constraint parsing, judging, boxes and prompts (pure functions)."""

import math

import pandas as pd
import pytest

from vlactl.errors import UsageError
from vlactl.rollout.constraints import KINDS, box, judge_steps, parse_constraint, prompted, start_gripper


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
