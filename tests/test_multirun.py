"""Hydra-style multirun (`-m`): sweeps expand to the cartesian product, lists stay one value, runs get their own
folders."""

import json

import pytest
from omegaconf import OmegaConf
from typer.testing import CliRunner

from vlactl.cli import app
from vlactl.errors import UsageError
from vlactl.multirun import expand


def test_sweeps_expand_to_the_product_and_lists_stay_whole():
    runs = expand(["model=hybrid", "constraint=gripper=open,height=low", "alpha=2,4", "layers=[backbone.2,expert.3]"],
                  named_by=("constraint",))
    assert [tag for _, tag in runs] == ["alpha-2", "alpha-4", "alpha-2", "alpha-4"]
    assert runs[3][0] == ["model=hybrid", "constraint='height=low'", "alpha=4", "layers=[backbone.2,expert.3]"]
    assert [tag for _, tag in expand(["layers=[backbone.1],[expert.0]"])] == ["layers-backbone.1", "layers-expert.0"]
    assert expand(["seed=3"]) == [(["seed=3"], "")]


def test_malformed_sweep_is_a_usage_error():
    with pytest.raises(UsageError, match="bad multirun override"):
        expand(["alpha=2,,4"])


def test_rollout_multirun_runs_every_combination_in_its_own_folder(tmp_path):
    result = CliRunner().invoke(app, [
        "rollout", "-m", "model=random", "tasks=[0]", "episodes_per_task=1", "max_steps=2", "workers=1",
        f"output_root={tmp_path}", "constraint=gripper=closed", "seed=0,1",
    ])
    assert result.exit_code == 0, result.output
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == [f"random_libero_spatial_gripper-closed_none_seed-{s}" for s in (0, 1)]
    for name, seed in zip(names, (0, 1)):
        summary = json.loads((tmp_path / name / "summary.json").read_text())
        assert summary["constraint"] == "gripper=closed" and OmegaConf.load(tmp_path / name / "config.yaml").seed == seed
