"""Multirun (`-m`) through Hydra's sweeper and launcher: sweeps expand to the cartesian product, lists stay one value,
runs get their own folders, and joblib and submitit_local write what the default launcher does."""

import json

import pandas as pd
import pytest
from omegaconf import OmegaConf
from typer.testing import CliRunner

from vlactl.cli import app
from vlactl.errors import UsageError
from vlactl.multirun import launch
from vlactl.rollout.runner import rollout_config

BASE = ["model=random", "tasks=[0]", "episodes_per_task=1", "max_steps=2", "workers=1"]


def test_sweeps_expand_to_the_product_and_lists_stay_whole(tmp_path):
    runs = []
    sweep_dir = f"hydra.sweep.dir={tmp_path}"
    launch("rollout", ["model=hybrid", "constraint=gripper=open,height=low", "alpha=2,4",
                       "layers=[backbone.2,expert.3]", sweep_dir],
           lambda items, tag: runs.append((items, tag)), rollout_config, named_by=("constraint",))
    assert [tag for _, tag in runs] == ["alpha-2", "alpha-4", "alpha-2", "alpha-4"]
    assert runs[3][0] == ["model=hybrid", "layers=[backbone.2,expert.3]", "constraint='height=low'", "alpha=4"]
    runs.clear()
    launch("rollout", ["layers=[backbone.1],[expert.0]", sweep_dir], lambda items, tag: runs.append(tag),
           rollout_config)
    assert runs == ["layers-backbone.1", "layers-expert.0"]
    assert list(tmp_path.iterdir()) == [tmp_path / "multirun.yaml"]  # no .hydra/ folders, no job logs
    runs.clear()  # a bracketed list of constraints is one value; beside another value, a sweep of two
    launch("rollout", ["constraint=[speed=low,height=high]", "seed=0,1", sweep_dir], lambda items, tag: runs.append(
        (rollout_config(items).constraint, tag)), rollout_config, named_by=("constraint",))
    assert runs == [("height=high,speed=low", "seed-0"), ("height=high,speed=low", "seed-1")]
    runs.clear()
    launch("rollout", ["constraint=[height=high,speed=low],gripper=open", sweep_dir], lambda items, tag: runs.append(
        rollout_config(items).constraint), rollout_config, named_by=("constraint",))
    assert runs == ["height=high,speed=low", "gripper=open"]


def test_bad_sweeps_and_launchers_are_usage_errors(tmp_path):
    with pytest.raises(UsageError, match="bad multirun override"):
        launch("rollout", ["alpha=2,,4"], print, rollout_config)
    with pytest.raises(UsageError, match="alpha="):  # checked before anything runs
        launch("rollout", ["alpha=2,abc"], print, rollout_config)
    with pytest.raises(UsageError, match="two constraints on height"):  # a fixed value too
        launch("rollout", ["constraint=[height=low,height=high]", "seed=0,1"], print, rollout_config)
    with pytest.raises(UsageError, match="bad multirun setting.*hydra/launcher=nope"):
        launch("rollout", ["seed=0,1", "hydra/launcher=nope", f"hydra.sweep.dir={tmp_path}"], print, rollout_config)
    result = CliRunner().invoke(app, ["rollout", *BASE, "hydra/launcher=joblib"])
    assert result.exit_code != 0 and isinstance(result.exception, UsageError) and "needs -m" in str(result.exception)


def _tables(root):
    """Every run folder's tables and summary, less the wall times."""
    out = {}
    for run in sorted(p for p in root.iterdir()):
        summary = json.loads((run / "summary.json").read_text())
        out[run.name] = (pd.read_parquet(run / "episodes.parquet").drop(columns="wall_s"),
                         pd.read_parquet(run / "steps.parquet"),
                         {key: value for key, value in summary.items() if "wall" not in key},
                         OmegaConf.load(run / "config.yaml"))
    return out


@pytest.fixture(scope="module")
def launched(tmp_path_factory):
    """launched(name): the run root of one 2 x 2 sweep under that launcher (run once per module)."""
    roots = {}

    def launch_with(launcher):
        if launcher not in roots:
            root, hydra = tmp_path_factory.mktemp(launcher), tmp_path_factory.mktemp(f"{launcher}-hydra")
            result = CliRunner().invoke(app, [
                "rollout", "-m", *BASE, f"output_root={root}", "constraint=gripper=closed", "method=none", "seed=0,1",
                "snap_gripper=true,false", f"hydra/launcher={launcher}", f"hydra.sweep.dir={hydra}",
                *(["hydra.launcher.n_jobs=2"] if launcher == "joblib" else []),
            ])
            assert result.exit_code == 0, result.output
            roots[launcher] = root
        return roots[launcher]

    return launch_with


def test_rollout_multirun_runs_every_combination_in_its_own_folder(launched):
    root = launched("basic")
    names = sorted(p.name for p in root.iterdir())
    assert names == sorted(f"random_libero_spatial_gripper-closed_none_seed-{s}_snap_gripper-{g}"
                           for s in (0, 1) for g in ("True", "False"))
    for name, (_, _, summary, config) in _tables(root).items():
        assert summary["constraint"] == "gripper=closed"
        assert name.endswith(f"seed-{config.seed}_snap_gripper-{config.snap_gripper}")


@pytest.mark.slow  # 8 more rollouts, in processes that each load the simulator
@pytest.mark.parametrize("launcher", ["joblib", "submitit_local"])
def test_launchers_write_what_the_default_launcher_writes(launched, launcher):
    expected, got = _tables(launched("basic")), _tables(launched(launcher))
    assert list(got) == list(expected)
    for name, (episodes, steps, summary, config) in got.items():
        pd.testing.assert_frame_equal(episodes, expected[name][0])
        pd.testing.assert_frame_equal(steps, expected[name][1])
        assert summary == expected[name][2]
        assert config == OmegaConf.merge(expected[name][3], {"output_root": config.output_root})
