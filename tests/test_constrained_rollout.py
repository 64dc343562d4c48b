"""Constrained rollouts end to end with the random test model: probes from collect + train-probes on a synthetic
dataset, then `vlactl rollout --constraint gripper=open --method control|prompt|none`."""

import dataclasses

import numpy as np
import pandas as pd
import pytest
import torch
from synthetic_demos import write_synthetic_demos
from typer.testing import CliRunner

from vlactl.cli import app
from vlactl.errors import UsageError
from vlactl.models.registry import tiny_policy
from vlactl.rollout.runner import rollout_config, run_rollout


@pytest.fixture(scope="module")
def probes(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("probes")
    demos = write_synthetic_demos(tmp / "demos", episodes=6, frames=8)
    runner = CliRunner()
    common = [f"cache_dir={tmp / 'cache'}", "threads=1"]
    result = runner.invoke(app, ["collect", "model=random", f"dataset={demos}", f"output_dir={tmp / 'acts'}", *common])
    assert result.exit_code == 0, result.output
    result = runner.invoke(app, ["train-probes", f"activations={tmp / 'acts'}", f"output_dir={tmp / 'run'}",
                                 "features=[gripper_action,dx,dy,dz,speed]", "cv_folds=2", "robustness_directions=2"])
    assert result.exit_code == 0, result.output
    return tmp / "run"


def rollout(root, *extra):
    return run_rollout(rollout_config(["model=random", "tasks=[0]", "episodes_per_task=1", "max_steps=6", "workers=1",
                                       f"output_root={root}", "constraint=gripper=open", "window=4", *extra]))


def test_control_keeps_the_steered_reading_in_the_box(probes, tmp_path):
    summary = rollout(tmp_path, "method=control", f"probes={probes}", "logit_margin=3", "box=state")
    out = tmp_path / "random_libero_spatial_gripper-open_control"
    steps = pd.read_parquet(out / "steps.parquet")
    assert steps["in_window"].tolist() == [True] * 4 + [False] * 2
    steered = steps.dropna(subset=["reading_after"])
    assert steered["t"].tolist() == [0, 2]  # the tiny model re-plans every 2 steps; only window steps are steered
    assert (steered["reading_after"] <= -3 + 1e-4).all()  # float32 rounding of x + u, as `plot readings` allows
    episodes = pd.read_parquet(out / "episodes.parquet")
    window = steps[steps["in_window"]]
    # open means an opening command: a snapped 0 holds the fingers where they are and is not judged open
    assert episodes["satisfaction"].iloc[0] == pytest.approx(float((window["gripper_action"] < 0).mean()))
    assert summary["method"] == "control" and summary["steered_layers"] and "satisfaction" in summary


def test_control_with_held_readings_still_lands_in_the_box(probes, tmp_path):
    summary = rollout(tmp_path, "method=control", f"probes={probes}", "logit_margin=3", "hold=[dx,dz]", "box=state")
    steps = pd.read_parquet(tmp_path / "random_libero_spatial_gripper-open_control" / "steps.parquet")
    assert (steps.dropna(subset=["reading_after"])["reading_after"] <= -3 + 1e-4).all()
    assert summary["held"] == ["dx", "dz"]
    with pytest.raises(UsageError, match="hold=.* not"):  # a run saved without holds is not resumed with them
        rollout(tmp_path, "method=control", f"probes={probes}", "hold=[dx]", "box=state")


@pytest.mark.parametrize("extra, message", [
    (["method=alpha", "hold=[dx]"], "needs method=control"),
    (["method=control", "hold=[gripper_action]"], "hold feature"),
    (["method=control", "hold=[droll]"], "no probe"),
    (["method=control", "hold=[dx]", "hold_tolerance=-1"], "hold_tolerance"),
])
def test_bad_holds_are_usage_errors(probes, tmp_path, extra, message):
    with pytest.raises(UsageError, match=message):
        rollout(tmp_path, f"probes={probes}", *extra)


def test_probes_of_another_model_are_refused_before_any_episode(probes, tmp_path):
    cfg = rollout_config(["model=random", "tasks=[0]", "episodes_per_task=1", f"output_root={tmp_path}",
                          "constraint=gripper=open", "method=control", f"probes={probes}"])
    with pytest.raises(UsageError, match="was trained on model 'hybrid', .*; this is 'autoregressive'"):
        run_rollout(cfg, load_policy=lambda name: tiny_policy("autoregressive"))
    assert not any(tmp_path.iterdir())  # no run folder, no worker started


def test_probes_of_other_weights_of_the_same_model_are_refused_before_any_episode(probes, tmp_path):
    import json
    import shutil

    from vlactl.steering.train_probes import PROBE_PROVENANCE

    checkpoint = tmp_path / "checkpoint"
    checkpoint.mkdir()
    tiny_policy("hybrid", seed=0).save_pretrained(checkpoint)
    fitted = tmp_path / "probes"
    shutil.copytree(probes, fitted)
    (fitted / PROBE_PROVENANCE).write_text(json.dumps({"model": "hybrid", "weights": "0123456789abcdef"}))
    cfg = rollout_config([f"model={checkpoint}", "tasks=[0]", "episodes_per_task=1", f"output_root={tmp_path / 'runs'}",
                          "constraint=gripper=open", "method=control", f"probes={fitted}"])
    with pytest.raises(UsageError, match=r"fitted on 'hybrid' \(weights 0123456789abcdef\), not on model=.*checkpoint"):
        run_rollout(cfg)
    assert not (tmp_path / "runs").exists()


@pytest.mark.slow
def test_prompt_and_none_record_satisfaction_without_steering(tmp_path):
    for method in ("none", "prompt"):
        rollout(tmp_path, f"method={method}")
        steps = pd.read_parquet(tmp_path / f"random_libero_spatial_gripper-open_{method}" / "steps.parquet")
        assert steps["reading_after"].isna().all() and steps["satisfied"].notna().sum() == 4
    # method=none acts as the unconstrained policy: judging an unconstrained run gives the same tables
    rollout(tmp_path, "constraint=none")
    rollout(tmp_path, "method=none", f"judge_from={tmp_path / 'random_libero_spatial'}", "run_name=judged")
    for table in ("episodes", "steps"):
        judged = pd.read_parquet(tmp_path / "judged" / f"{table}.parquet").drop(columns="wall_s", errors="ignore")
        ran = pd.read_parquet(tmp_path / f"random_libero_spatial_gripper-open_none" / f"{table}.parquet")
        pd.testing.assert_frame_equal(judged, ran.drop(columns="wall_s", errors="ignore"))
    with pytest.raises(UsageError, match="ran with seed=0, not 1"):
        rollout(tmp_path, "method=none", f"judge_from={tmp_path / 'random_libero_spatial'}", "run_name=j2", "seed=1")
    assert not (tmp_path / "j2").exists()  # refused before the run folder is made


@pytest.mark.slow
def test_a_prompt_the_model_reads_alike_is_judged_from_its_run(tmp_path):
    rollout(tmp_path, "constraint=height=low", "method=prompt")
    source = tmp_path / "random_libero_spatial_height-low_prompt"
    rollout(tmp_path, "constraint=height=high", "method=prompt")  # "high" is as unknown as "low"
    rollout(tmp_path, "constraint=height=high", "method=prompt", f"judge_from={source}", "run_name=judged")
    for table in ("episodes", "steps"):
        judged = pd.read_parquet(tmp_path / "judged" / f"{table}.parquet").drop(columns="wall_s", errors="ignore")
        ran = pd.read_parquet(tmp_path / "random_libero_spatial_height-high_prompt" / f"{table}.parquet")
        pd.testing.assert_frame_equal(judged, ran.drop(columns="wall_s", errors="ignore"))
    # the tiny model reads 12 tokens, none of the prompt; one that reads them all knows "the" of "keep the gripper open"
    cfg = rollout_config(["model=random", "tasks=[0]", "episodes_per_task=1", "max_steps=6", "workers=1", "window=4",
                          f"output_root={tmp_path}", "constraint=gripper=open", "method=prompt",
                          f"judge_from={source}", "run_name=j2"])
    with pytest.raises(UsageError, match="reads otherwise than"):
        run_rollout(cfg, load_policy=lambda name: tiny_policy("hybrid", max_text_tokens=40))
    assert not (tmp_path / "j2").exists()


@pytest.mark.slow
def test_baselines_under_gripper_closed_start_with_the_gripper_closed(tmp_path):
    rollout(tmp_path, "constraint=gripper=closed", "method=none")
    out = tmp_path / "random_libero_spatial_gripper-closed_none"
    first = pd.read_parquet(out / "steps.parquet")["gripper"].iloc[0]
    opened = rollout(tmp_path, "constraint=none", "run_name=open")
    assert opened["start_gripper"] == "open"
    assert first < pd.read_parquet(tmp_path / "open" / "steps.parquet")["gripper"].iloc[0] - 0.5
    assert pd.read_parquet(out / "episodes.parquet")["start_gripper"].tolist() == ["closed"]


@pytest.mark.parametrize("extra, message", [
    (["method=control"], "needs probes="),
    (["method=steer"], "method"),
    (["constraint=none", "method=prompt"], "needs a constraint"),
    (["constraint=speed=slow"], "unknown constraint 'speed=slow'"),
    (["method=meandiff", "probes=/nonexistent"], "not a probe run folder"),
    (["start_gripper=shut"], "start_gripper"),
    (["constraint=gripper=closed", "method=none", "judge_from=/nonexistent"], "cannot stand in"),
    (["method=filter", "judge_from=/nonexistent"], "method=none or prompt, not"),
    (["constraint=speed=low", "method=filter", "speed_margin=1.2"], r"speed_margin must be in \[0, 1\)"),
])
def test_bad_input_is_a_usage_error(tmp_path, extra, message):
    with pytest.raises(UsageError, match=message):
        rollout(tmp_path, *extra)


def test_plot_readings_puts_every_controlled_reading_in_the_box(probes, tmp_path):
    demos, out = probes.parent / "demos", tmp_path / "fig"
    result = CliRunner().invoke(app, [
        "plot", "readings", "model=random", f"probes={probes}", f"dataset={demos}", f"cache_dir={probes.parent / 'cache'}",
        "frames=8", "zmin=-4", "zmax=-3", "alpha=2", f"output_dir={out}", "formats=[png]", "threads=1",
    ])
    assert result.exit_code == 0, result.output
    table = pd.read_parquet(out / "readings.parquet")
    assert sorted(table["condition"].unique()) == ["alpha", "control", "none"]
    controlled = table[table["condition"] == "control"]["reading"]
    assert len(controlled) == 8 and controlled.between(-4 - 1e-4, -3 + 1e-4).all()  # float32 rounding of x + u
    none = table[table["condition"] == "none"].set_index("frame")["reading"]
    pushed = table[table["condition"] == "alpha"].set_index("frame")["reading"]
    assert (pushed - none > 0).all()  # a positive alpha moves every reading up along W
    assert (out / "fig3_readings.png").stat().st_size > 0


@pytest.mark.slow
def test_mean_difference_pushes_by_alpha_along_its_direction(probes, tmp_path):
    rollout(tmp_path, "method=meandiff", f"probes={probes}", f"activations={probes.parent / 'acts'}", "alpha=5")
    steps = pd.read_parquet(tmp_path / "random_libero_spatial_gripper-open_meandiff" / "steps.parquet")
    steered = steps.dropna(subset=["u_norm"])
    assert steered["t"].tolist() == [0, 2] and np.allclose(steered["u_norm"], 5.0, rtol=1e-4)
    assert (steered["u_norm_all"] >= steered["u_norm"] - 1e-6).all() and (steered["active_share"] == 1.0).all()


def test_mean_difference_splits_on_the_feature_it_pushes_along(probes):
    from vlactl.rollout.constraints import parse_constraint
    from vlactl.rollout.plan import mean_difference_directions
    from vlactl.steering.activations import ActivationStore
    from vlactl.steering.controller import mean_difference

    acts = probes.parent / "acts"
    store = ActivationStore(acts)
    x = store.load(["expert.0"])[0]
    for box, feature in (("action", "dz"), ("state", "z")):
        cfg = rollout_config(["model=random", "method=meandiff", "constraint=height=low", f"box={box}",
                              f"activations={acts}"])
        values = store.labels[feature].to_numpy(dtype=float)
        upper = values > (0.0 if feature == "dz" else np.median(values))
        got = mean_difference_directions(cfg, parse_constraint("height=low"), ["expert.0"])["expert.0"]
        assert np.allclose(got, mean_difference(x, torch.as_tensor(upper)).float(), atol=1e-6)


def test_default_layer_is_the_best_one_that_can_move_the_actions(probes, tmp_path):
    import shutil

    table = pd.read_parquet(probes / "metrics.parquet")
    assert dict(zip(table["layer"], table["steerable"]))["backbone.1"] is False  # its output feeds nothing
    run = tmp_path / "run"
    shutil.copytree(probes, run)
    table["balanced_accuracy"] = np.where(table["layer"] == "backbone.1", 1.0, 0.6)  # the best probe is not steerable
    table.to_parquet(run / "metrics.parquet")
    summary = rollout(tmp_path, "method=control", f"probes={run}")
    assert "backbone.1" not in summary["steered_layers"] and len(summary["steered_layers"]) == 1


def test_a_layer_group_steers_each_of_its_steerable_layers(probes, tmp_path):
    table = pd.read_parquet(probes / "metrics.parquet")
    expert = sorted(set(table.loc[table["steerable"] & table["layer"].str.startswith("expert."), "layer"]))
    assert expert
    summary = rollout(tmp_path, "method=control", f"probes={probes}", "layers=expert")
    assert sorted(summary["steered_layers"]) == expert


def test_probes_fitted_at_the_action_set_steer_there(tmp_path):
    """A probe run of `pooling=action` (the expert's action tokens here) is pushed at that set in a rollout."""
    demos = write_synthetic_demos(tmp_path / "demos", episodes=6, frames=8)
    runner, common = CliRunner(), [f"cache_dir={tmp_path / 'cache'}", "threads=1"]
    result = runner.invoke(app, ["collect", "model=random", f"dataset={demos}", f"output_dir={tmp_path / 'acts'}",
                                 "pooling=action", "layers=[expert.0,expert.1]", *common])
    assert result.exit_code == 0, result.output
    result = runner.invoke(app, ["train-probes", f"activations={tmp_path / 'acts'}", f"output_dir={tmp_path / 'run'}",
                                 "features=[gripper_action,dx,dy,dz]", "cv_folds=2", "robustness_directions=2"])
    assert result.exit_code == 0, result.output
    summary = rollout(tmp_path, "method=control", f"probes={tmp_path / 'run'}", "constraint=height=high",
                      "layers=[expert.0]", "metres_per_unit=0.012", "height_margin=0", "run_name=pushed")
    steps = pd.read_parquet(tmp_path / "pushed" / "steps.parquet").dropna(subset=["bound_lo"])
    assert summary["steered_layers"] == ["expert.0"] and (steps["passes"] >= 1).any()
    assert (steps.loc[steps["passes"] >= 1, "u_norm"] > 0).all()


@pytest.mark.parametrize("constraint", ["height=high", "gripper=closed"])
def test_action_boxes_push_only_when_the_prediction_breaks_the_bound(probes, tmp_path, constraint):
    rollout(tmp_path, "method=control", f"probes={probes}", f"constraint={constraint}", "layers=[backbone.1]",
            "metres_per_unit=0.012", "height_margin=0", "run_name=run")
    steps = pd.read_parquet(tmp_path / "run" / "steps.parquet").dropna(subset=["bound_lo"])
    assert steps["t"].tolist() == [0, 2]  # every re-plan in the window is bounded
    inside = (steps["action_before"] >= steps["bound_lo"]) & (steps["action_before"] <= steps["bound_hi"])
    assert (steps["passes"][inside] == 0).all() and (steps["passes"][~inside] >= 1).all()
    if constraint == "height=high":  # at the start height the barrier asks for no descent at all
        assert steps["bound_lo"].iloc[0] == pytest.approx(0.0)


def test_control_pause_bounds_the_translation_to_a_stop_where_the_barrier_binds(probes, tmp_path):
    summary = rollout(tmp_path, "method=control", f"probes={probes}", "constraint=height=high", "pause=true",
                      "layers=[expert.0]", "metres_per_unit=0.012", "height_margin=0", "run_name=run")
    assert summary["method"] == "control" and summary["pause"] and summary["held"] == ["gripper_action"]
    steps = pd.read_parquet(tmp_path / "run" / "steps.parquet").dropna(subset=["bound_lo"])
    inside = (steps["action_before"] >= steps["bound_lo"]) & (steps["action_before"] <= steps["bound_hi"])
    stopped = steps["paused"].astype(bool)
    assert stopped.tolist() == (~inside).tolist()  # a stop only where the barrier binds
    paused = steps[stopped]
    assert len(paused) and (paused["passes"] >= 1).all()
    # pushed along the predicted motion towards a stop: the commanded translation slower than unsteered
    assert (paused["stop_after"] < paused["stop_before"]).all()
    assert steps.loc[~stopped, "stop_before"].isna().all()


def test_the_stop_pushes_the_translation_and_the_yaw_read_outs_a_run_has():
    from vlactl.rollout.constraints import parse_constraint
    from vlactl.rollout.plan import steered_features

    high, low = parse_constraint("height=high"), parse_constraint("speed=low")
    assert steered_features(high, "action", "control") == ("dz",)
    present = {"dx", "dy", "dz", "droll", "dpitch", "dyaw"}  # the tilt's read-outs are left alone
    assert steered_features(high, "action", "control", True, present) == ("dz", "dx", "dy", "dyaw")
    assert steered_features(low, "action", "control", True, {"dx", "dy", "dz"}) == ("dx", "dy", "dz")
    assert steered_features(parse_constraint("gripper=open"), "action", "control", True, {"dyaw"}) == \
        ("gripper_action",)  # not pausable: no stop


def test_the_stop_takes_its_read_outs_from_the_stop_probes(probes, tmp_path):
    """stop_probes=: the stop's read-outs (height's dz among them) from that run; speed and the holds from probes=."""
    from vlactl.rollout.constraints import parse_constraint
    from vlactl.rollout.plan import steering
    from vlactl.steering.probe_file import load_probe, save_probe
    from vlactl.steering.train_probes import probe_filename

    result = CliRunner().invoke(app, ["train-probes", f"activations={probes.parent / 'acts'}",
                                      f"output_dir={tmp_path / 'stop'}", "features=[dx,dy,dz,gripper_action,speed]",
                                      "family=partial", "cv_folds=2", "robustness_directions=2"])
    assert result.exit_code == 0, result.output
    cfg = rollout_config(["model=random", "method=control", "constraint=height=high", "pause=true", f"probes={probes}",
                          f"stop_probes={tmp_path / 'stop'}", "layers=[expert.0]", "metres_per_unit=0.012"])
    plan = steering(cfg, parse_constraint("height=high", cfg.window))
    assert [p.feature for p in plan.probes] == ["dz", "dx", "dy"]
    for probe in plan.probes:
        stop = load_probe(tmp_path / "stop" / "probes" / probe_filename("expert.0", probe.feature))
        shipped = load_probe(probes / "probes" / probe_filename("expert.0", probe.feature))
        assert torch.equal(probe.weight, stop.weight) and not torch.equal(probe.weight, shipped.weight)
    assert [p.feature for p in plan.holds] == ["gripper_action"]
    held = load_probe(probes / "probes" / probe_filename("expert.0", "gripper_action"))
    assert torch.equal(plan.holds[0].weight, held.weight)
    with pytest.raises(UsageError, match="stop_probes=.* needs pause=true"):
        steering(rollout_config(["model=random", "method=control", "constraint=height=high", f"probes={probes}",
                                 f"stop_probes={tmp_path / 'stop'}"]), parse_constraint("height=high", cfg.window))
    for path in (tmp_path / "stop" / "probes").iterdir():  # stop probes fitted at another read-out set
        save_probe(dataclasses.replace(load_probe(path), pooling="action"), path)
    with pytest.raises(UsageError, match="read action and prefix: fit them on activations of one pooling"):
        steering(cfg, parse_constraint("height=high", cfg.window))


# --- several constraints at once ----------------------------------------------------------------------------------

BOTH = ["constraint=[speed=low,height=high]", "metres_per_unit=0.012", "speed_threshold=0.02", "height_margin=0"]


def test_several_constraints_under_control_are_each_bounded_and_named(probes, tmp_path):
    from omegaconf import OmegaConf

    summary = rollout(tmp_path, "method=control", f"probes={probes}", *BOTH)
    out = tmp_path / "random_libero_spatial_height-high_speed-low_control"  # every constraint named, KINDS order
    assert OmegaConf.load(out / "config.yaml").constraint == "height=high,speed=low"  # saved in one canonical form
    episodes, steps = pd.read_parquet(out / "episodes.parquet"), pd.read_parquet(out / "steps.parquet")
    assert episodes["constraint"].tolist() == ["height=high,speed=low"]
    for column in ("satisfaction", "satisfaction_height", "satisfaction_speed"):
        assert 0 <= episodes[column].iloc[0] <= 1
    window = steps[steps["in_window"]]
    every = window["satisfied_height"].fillna(True) & window["satisfied_speed"].fillna(True)
    assert episodes["satisfaction"].iloc[0] == pytest.approx(float(every.mean()))
    assert summary["constraint"] == "height=high,speed=low" and summary["held"] == ["gripper_action"]
    assert set(summary["constraints"]) == {"height=high", "speed=low"}
    assert summary["constraints"]["speed=low"]["satisfaction"] == pytest.approx(episodes["satisfaction_speed"].iloc[0])
    bounded = steps.dropna(subset=["bound_lo_height"])
    assert bounded["t"].tolist() == [0, 2] and bounded["bound_lo_speed"].notna().all()  # each re-plan, both bounds
    inside = pd.Series(True, index=bounded.index)
    for feature in ("height", "speed"):
        q = bounded[f"action_before_{feature}"]
        inside &= (q >= bounded[f"bound_lo_{feature}"]) & (q <= bounded[f"bound_hi_{feature}"])
    assert (bounded["passes"][inside] == 0).all() and (bounded["passes"][~inside] >= 1).all()
    assert "action_before" not in steps and "constraint_value" not in steps  # no column that names one of them only
    again = rollout(tmp_path, "method=control", f"probes={probes}", *BOTH[1:], "constraint=height=high,speed=low")
    assert again["episodes"] == 1  # the same run in another spelling: resumed, not refused


def test_several_constraints_under_the_filter_keep_both_bounds_where_they_can(probes, tmp_path):
    from vlactl.rollout.constraints import Bounds, action_bound, parse_constraints

    summary = rollout(tmp_path, "method=filter", *BOTH, "window=null")
    steps = pd.read_parquet(tmp_path / "random_libero_spatial_height-high_speed-low_filter" / "steps.parquet")
    high, low = parse_constraints("height=high,speed=low")
    bounds = Bounds(speed_threshold=0.02, metres_per_unit=0.012)
    feasible = 0
    for row in steps.itertuples():
        lo = action_bound(high, row.z, steps["z"].iloc[0], bounds)[0]
        fast = action_bound(low, row.z, 0.02, bounds)[1]
        if lo <= fast:  # a rise the speed bound allows
            feasible += 1
            assert row.dz >= lo - 1e-9 and np.linalg.norm([row.dx, row.dy, row.dz]) <= fast + 1e-9
    assert feasible >= 1
    assert set(summary["constraints"]) == {"height=high", "speed=low"} and summary["method"] == "filter"


@pytest.mark.parametrize("extra, message", [
    (["method=alpha"], "method=alpha takes one constraint, not 2"),
    (["method=meandiff"], "method=meandiff takes one constraint"),
    (["method=control", "box=state"], "box=state takes one constraint"),
    (["method=control", "hold=[x,y,z,roll,pitch,yaw,gripper]", "hold_tolerance=0.1"],
     r"hold=\[.*\] with hold_tolerance=0.1: at most 6 features can be held"),
    (["method=control", "hold=[speed]"], "unknown hold feature 'speed'"),
])
def test_several_constraints_where_they_cannot_go_are_usage_errors(probes, tmp_path, extra, message):
    with pytest.raises(UsageError, match=message):
        rollout(tmp_path, f"probes={probes}", *BOTH, *extra)
    assert not any(tmp_path.iterdir())  # no run folder


@pytest.mark.parametrize("constraint, message", [
    ("[height=high,speed=slow]", "unknown constraint 'speed=slow' in constraint=[height=high,speed=slow]; allowed: "),
    ("[height=low,height=high]", "two constraints on height (height=low, height=high); one per feature"),
    ("[]", "names no constraint"),
])
def test_bad_constraint_lists_on_the_command_line_are_one_line(tmp_path, constraint, message):
    import subprocess
    import sys

    for multirun in ([], ["-m"]):
        res = subprocess.run([sys.executable, "-m", "vlactl.cli", "rollout", *multirun, "model=random",
                              f"constraint={constraint}", f"output_root={tmp_path}"],
                             capture_output=True, text=True, timeout=120)
        lines = [line for line in res.stderr.splitlines() if line.strip() and "robosuite" not in line]
        assert res.returncode == 2 and lines == [f"error: {lines[0][7:]}"] and message in lines[0], res.stderr
        assert not any(tmp_path.iterdir())


def test_a_held_gripper_is_kept_on_the_action_while_speed_is_pushed(probes):
    from vlactl.rollout.constrained import ConstrainedAgent
    from vlactl.rollout.constraints import parse_constraint
    from vlactl.rollout.plan import steering
    from vlactl.steering.steer import Constraint as ProbeBox

    cfg = rollout_config(["model=random", "constraint=speed=low", "method=control", f"probes={probes}",
                          "speed_threshold=0.2", "metres_per_unit=0.01", "layers=[expert.0]"])
    plan = steering(cfg, parse_constraint(cfg.constraint))
    assert {p.feature for p in plan.probes} == {"dx", "dy", "dz"}  # speed is pushed through the translation
    assert {p.feature for p in plan.holds} == {"gripper_action"}
    agent = ConstrainedAgent(tiny_policy("hybrid"), parse_constraint(cfg.constraint), plan)
    agent._held = [ProbeBox(p, 0.0, 0.0, relative=True) for p in plan.holds]  # what reset() builds
    chunk = np.zeros((5, 7))
    chunk[:, 6] = -1.0  # open throughout: kept open, by the gripper-action probes, no longer held by reading alone
    (kept,) = agent._gripper_kept(chunk, 3)
    assert (kept.feature, kept.value) == ("gripper", "open") and kept.window > 3
    speed = parse_constraint(cfg.constraint)
    agent._weights = {"speed": {"dx": 1.0, "dy": 0.0, "dz": 0.0}, "gripper": {"gripper_action": 1.0}}
    grip = [b for b in agent._push_boxes({"speed": 0.1, "gripper": 0.0}, [speed, kept])
            if b.probe.feature == "gripper_action"]
    assert len(grip) == len(plan.holds) and not any(b is h for b in grip for h in agent._held)  # pushed, not held
    chunk[2, 6] = 1.0  # the policy itself switches within the chunk: nothing kept, the reading hold stays
    assert agent._gripper_kept(chunk, 3) == []
    boxes = agent._push_boxes({"speed": 0.1}, [speed])
    assert all(any(b is h for b in boxes) for h in agent._held)
