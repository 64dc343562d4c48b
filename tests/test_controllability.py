"""`vlactl controllability`, `vlactl plot controllability` and the rollout's default layers, with the random test
model on a tiny synthetic dataset."""

import shutil

import numpy as np
import pandas as pd
import pytest
import torch
from synthetic_demos import write_synthetic_demos
from typer.testing import CliRunner

from vlactl.cli import app
from vlactl.config import load_policy_stage_config
from vlactl.env.features import ACTION_FEATURES
from vlactl.errors import UsageError
from vlactl.models.registry import tiny_policy
from vlactl.rollout.constraints import parse_constraint
from vlactl.rollout.plan import _steered_layers, steering
from vlactl.rollout.runner import rollout_config
from vlactl.steering.collect import frame_batch, model_frames, spread
from vlactl.steering.controllability import run_controllability
from vlactl.steering.probe_file import load_probe, save_probe
from vlactl.steering.sweep import _predict
from vlactl.steering.train_probes import METRICS_NAME, probe_filename

FEATURES = ["z", "gripper_action"]


@pytest.fixture(scope="module")
def probe_runs(tmp_path_factory):
    """demos, and two probe runs of the same activations: observability (L2 1) and steering (L2 1e4)."""
    root = tmp_path_factory.mktemp("controllability")
    demos = write_synthetic_demos(root / "demos", episodes=6, frames=8)
    runner = CliRunner()
    acts = root / "acts"
    result = runner.invoke(app, ["collect", "model=random", f"dataset={demos}", f"output_dir={acts}",
                                 f"cache_dir={root / 'cache'}", "threads=1"])
    assert result.exit_code == 0, result.output
    runs = []
    for name, l2 in (("observe", 1), ("steer", 1e4)):
        result = runner.invoke(app, ["train-probes", f"activations={acts}", f"output_dir={root / name}",
                                     f"features=[{','.join(FEATURES)}]", f"logistic_l2={l2}", "cv_folds=2",
                                     "robustness_directions=2"])
        assert result.exit_code == 0, result.output
        runs.append(root / name)
    return demos, runs


def measure(demos, probes, out, *extra):
    cfg = load_policy_stage_config("controllability", [
        "model=random", f"dataset={demos}", f"probes={probes}", f"output_dir={out}",
        f"cache_dir={out.parent / 'cache'}", "frames=6", "batch_size=4", "threads=1", *extra,
    ])
    return run_controllability(cfg)


def test_a_row_per_layer_group_and_feature_written_into_the_probe_run(probe_runs, tmp_path):
    demos, (probes, _) = probe_runs
    out = measure(demos, probes, tmp_path / "map")
    table = pd.read_parquet(out / "controllability.parquet")
    steerable = tiny_policy("hybrid").steerable_layers()  # backbone.0, expert.0, expert.1
    singles = table[~table["group"]]
    assert sorted(zip(singles["layer"], singles["feature"])) == sorted((l, f) for l in steerable for f in FEATURES)
    # expert has two steerable layers: a group row; backbone has one, which its single-layer row already is
    assert sorted(table[table["group"]]["layer"]) == ["expert", "expert"]
    assert (table["n_frames"] == 6).all() and (table["n_targets"] == 4).all()
    assert set(table[table["feature"] == "z"]["output"]) == {"dz"}
    assert table[table["feature"] == "z"]["cross_share"].isna().all()
    cross = table[table["feature"] == "gripper_action"]["cross_share"].dropna()
    assert ((cross >= 0) & (cross <= 1)).all()
    # what else each push moves: every predicted action column but the one it steers
    leaks = table.set_index("feature")[[f"leak_{c}" for c in ACTION_FEATURES]]
    assert leaks.loc["z", "leak_dz"].isna().all() and leaks.loc["gripper_action", "leak_gripper_action"].isna().all()
    assert leaks.loc["z", ["leak_dx", "leak_droll", "leak_dpitch", "leak_gripper_action"]].notna().all().all()
    # every steerable layer reaches the actions: the push moves the prediction
    assert (table["gain"].abs() > 1e-6).all() and (table["u_norm"] > 0).all()
    pd.testing.assert_frame_equal(pd.read_parquet(probes / "controllability.parquet"), table)
    points = pd.read_parquet(out / "points.parquet")
    assert len(points) == len(table) * 6 * 4


def test_features_measured_apart_add_up_in_the_probe_run(probe_runs, tmp_path):
    demos, (source, _) = probe_runs
    probes = tmp_path / "probes"
    shutil.copytree(source, probes)
    for feature, targets in (("z", "[-0.1,0.1]"), ("gripper_action", "[-5,5]")):  # each in its own units
        measure(demos, probes, tmp_path / feature, f"features=[{feature}]", f"targets={targets}", "groups=false")
    table = pd.read_parquet(probes / "controllability.parquet")
    assert sorted(table["feature"].unique()) == ["gripper_action", "z"]
    assert set(table[table["feature"] == "z"]["n_targets"]) == {2}


def test_the_shipped_probes_table_is_left_as_make_probes_made_it(probe_runs, tmp_path, monkeypatch):
    from vlactl.steering import controllability

    demos, (source, _) = probe_runs
    shipped = tmp_path / "data" / "probes"
    probes = shipped / "hybrid" / "steer"
    shutil.copytree(source, probes)
    (probes / "controllability.parquet").unlink(missing_ok=True)
    monkeypatch.setattr(controllability, "SHIPPED_PROBES", shipped)
    out = measure(demos, probes, tmp_path / "map", "features=[z]", "groups=false")
    assert (out / "controllability.parquet").is_file()
    assert not (probes / "controllability.parquet").exists()  # a rollout's default layers stay the shipped ones


def test_gain_has_the_sign_of_the_push(probe_runs, tmp_path):
    """A z probe at expert.1 along the direction that raises the predicted dz: raising its reading raises dz (gain
    > 0); the same probe negated reads the other way, so the same push lowers it (gain < 0). A gripper probe along
    that direction raises dz too: its leak into dz has the same sign."""
    demos, (source, _) = probe_runs
    vla = tiny_policy("hybrid")
    frames = model_frames(vla, demos, tmp_path / "cache")
    obs = frame_batch(frames, spread(len(frames), 6))
    direction = torch.randn(vla.layer_width("expert.1"), generator=torch.Generator().manual_seed(0))
    direction /= direction.norm()
    rise = [(_predict(vla, obs, "expert.1", s * 0.05 * direction)[:, 2]).mean() for s in (1, -1)]
    direction *= float(np.sign(rise[0] - rise[1]))
    gains, leaks = [], []
    for sign in (1, -1):
        probes = tmp_path / f"probes{sign}"
        shutil.copytree(source, probes)
        for feature in ("z", "gripper_action"):
            path = probes / "probes" / probe_filename("expert.1", feature)
            probe = load_probe(path)
            probe.weight = sign * direction.double()
            save_probe(probe, path)
        table = pd.read_parquet(measure(demos, probes, tmp_path / f"map{sign}", "groups=false",
                                        "targets=[-0.05,0.05]") / "controllability.parquet")
        rows = table[table["layer"] == "expert.1"].set_index("feature")
        gains.append(float(rows.loc["z", "gain"]))
        leaks.append(float(rows.loc["gripper_action", "leak_dz"]))
    assert gains[0] > 0 > gains[1] and leaks[0] > 0 > leaks[1]


def test_an_interrupted_run_resumes_from_its_finished_batches(probe_runs, tmp_path, monkeypatch):
    from vlactl.steering import offline

    demos, (probes, _) = probe_runs
    args = ("features=[z]", "targets=[-1,1]")
    whole = pd.read_parquet(measure(demos, probes, tmp_path / "whole", *args) / "points.parquet")
    written, write = [], offline.atomic_write_parquet

    def stop_after_one_batch(path, table):
        if written:
            raise KeyboardInterrupt
        written.append(path.name)
        write(path, table)

    monkeypatch.setattr(offline, "atomic_write_parquet", stop_after_one_batch)
    with pytest.raises(KeyboardInterrupt):
        measure(demos, probes, tmp_path / "resumed", *args)
    monkeypatch.setattr(offline, "atomic_write_parquet", lambda path, table: written.append(path.name)
                        or write(path, table))
    points = pd.read_parquet(measure(demos, probes, tmp_path / "resumed", *args) / "points.parquet")
    assert written == ["frames000000.parquet", "frames000004.parquet"]  # the first batch once, then the second
    pd.testing.assert_frame_equal(points, whole)


def test_rollout_default_layers_follow_the_table(probe_runs, tmp_path, capsys):
    demos, (source, _) = probe_runs
    metrics = pd.read_parquet(source / METRICS_NAME)
    rows = metrics[metrics["feature"] == "gripper_action"]
    old_rule = _steered_layers(None, rows)

    def table(scores):
        return pd.DataFrame({"layer": list(scores), "gain": [g for g, _ in scores.values()],
                             "r2": [r for _, r in scores.values()]})

    assert _steered_layers(None, rows, table({"backbone.0": (0.1, 0.9), "expert": (-0.5, 0.8),
                                              "expert.1": (2.0, 0.1)})) == ["expert.0", "expert.1"]
    assert _steered_layers(None, rows, table({"backbone.0": (-0.3, 0.9), "expert": (0.5, 0.1)})) == ["backbone.0"]
    assert _steered_layers(None, rows, table({"expert.0": (0.0, np.nan)})) == old_rule  # nothing moved: old rule
    assert _steered_layers(None, rows, None) == old_rule
    assert _steered_layers(["expert.0"], rows, table({"backbone.0": (1.0, 1.0)})) == ["expert.0"]  # asked wins

    # end to end: the probe run's own table decides what layers=null steers
    probes = tmp_path / "probes"
    shutil.copytree(source, probes)
    (probes / "controllability.parquet").unlink(missing_ok=True)  # the tests before measured the shared run

    def steered():
        cfg = rollout_config(["model=random", "constraint=gripper=closed", "method=control", f"probes={probes}",
                              f"demos={demos}", "metres_per_unit=1.0"])
        return [p.layer for p in steering(cfg, parse_constraint(cfg.constraint)).probes]

    capsys.readouterr()
    assert steered() == old_rule
    assert "no controllability rows for gripper_action" in capsys.readouterr().err  # the fallback is said
    table = pd.read_parquet(measure(demos, probes, tmp_path / "map", "features=[gripper_action]")
                            / "controllability.parquet")
    score = table["gain"].abs() * table["r2"]
    best = table.loc[score.idxmax(), "layer"]
    capsys.readouterr()
    assert steered() == (["expert.0", "expert.1"] if best == "expert" else [best])
    assert "no controllability rows" not in capsys.readouterr().err
    # probes retrained since the table was measured: the table is ignored
    pd.read_parquet(probes / METRICS_NAME).assign(r2=0.5).to_parquet(probes / METRICS_NAME)
    retrained = pd.read_parquet(probes / METRICS_NAME)
    assert steered() == _steered_layers(None, retrained[retrained["feature"] == "gripper_action"])


def test_plot_two_runs_side_by_side(probe_runs, tmp_path):
    demos, (observe, steer) = probe_runs
    outs = [measure(demos, probes, tmp_path / name, "targets=[-1,1]") for name, probes in
            (("observe", observe), ("steer", steer))]
    result = CliRunner().invoke(app, ["plot", "controllability", f"run_dir={outs[0]}", f"compare={outs[1]}",
                                      "formats=[png]"])
    assert result.exit_code == 0, result.output
    assert (outs[0] / "figures" / "controllability.png").stat().st_size > 0


def test_choose_into_takes_each_features_probes_from_the_run_that_moves_it_most(probe_runs, tmp_path):
    demos, (observe, steer) = probe_runs
    runs = [tmp_path / "observe", tmp_path / "steer"]
    for source, run in zip((observe, steer), runs):
        shutil.copytree(source, run)
        (run / "controllability.parquet").unlink(missing_ok=True)
    chosen = tmp_path / "chosen"
    assert measure(demos, f"[{runs[0]},{runs[1]}]", tmp_path / "maps", f"choose_into={chosen}") == chosen
    choice = pd.read_parquet(chosen / "choice.parquet")
    assert sorted(choice["feature"].unique()) == sorted(FEATURES) and choice.groupby("feature")["chosen"].sum().eq(1).all()
    metrics = pd.read_parquet(chosen / METRICS_NAME)
    for _, win in choice[choice["chosen"]].iterrows():
        best = choice[choice["feature"] == win["feature"]]["score"].max()
        assert win["score"] == best
        rows = metrics[metrics["feature"] == win["feature"]]
        source = pd.read_parquet(f"{win['run']}/{METRICS_NAME}")
        assert rows["probe"].tolist() == source[source["feature"] == win["feature"]]["probe"].tolist()
        for probe in rows["probe"]:  # the winner's own probe files, bit for bit
            assert (chosen / probe).read_bytes() == (tmp_path / win["run"] / probe).read_bytes()
    # its controllability rows are current for the assembled metrics: a rollout takes its layers from them
    from vlactl.steering.controllability import controllability_rows
    assert all(controllability_rows(chosen, f) is not None for f in FEATURES)


@pytest.mark.parametrize("extra, message", [
    (["probes=null"], "needs|which probes"),
    (["choose_into=/tmp/x"], "several probe runs"),
    (["targets=[1]"], "two or more different"),
    (["targets=[0,1]"], "non-zero"),
    (["features=[dyaw]"], "no probes of feature 'dyaw'"),
    (["probes=/nonexistent"], "'/nonexistent' is not a probe run folder"),
])
def test_bad_input_is_a_usage_error(probe_runs, tmp_path, extra, message):
    demos, (probes, _) = probe_runs
    with pytest.raises(UsageError, match=message):
        measure(demos, probes, tmp_path / "map", *extra)
