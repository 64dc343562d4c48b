"""`vlactl sweep` and `vlactl plot sweep` with the random test model on a tiny synthetic dataset."""

import numpy as np
import pandas as pd
import pytest
from synthetic_demos import write_synthetic_demos
from typer.testing import CliRunner

from vlactl.cli import app
from vlactl.config import load_policy_stage_config
from vlactl.errors import UsageError
from vlactl.models.registry import tiny_policy
from vlactl.steering.sweep import run_sweep


@pytest.fixture(scope="module")
def demos(tmp_path_factory):
    return write_synthetic_demos(tmp_path_factory.mktemp("demos") / "synthetic", episodes=6, frames=8)


def sweep(demos, out, *extra):
    cfg = load_policy_stage_config("sweep", [
        "model=random", f"dataset={demos}", f"output_dir={out}", f"cache_dir={out.parent / 'cache'}", "frames=6",
        "batch_size=4", "threads=1", "alphas=[-3,3]", *extra,
    ])
    return run_sweep(cfg)


def test_sweep_along_probe_directions_and_plot(demos, tmp_path):
    runner = CliRunner()
    acts, probes = tmp_path / "acts", tmp_path / "probes"
    common = [f"cache_dir={tmp_path / 'cache'}", "threads=1"]
    assert runner.invoke(app, ["collect", "model=random", f"dataset={demos}", f"output_dir={acts}", *common]).exit_code == 0
    result = runner.invoke(app, ["train-probes", f"activations={acts}", f"output_dir={probes}", "features=[dyaw]",
                                 "cv_folds=2", "robustness_directions=2"])
    assert result.exit_code == 0, result.output
    out = sweep(demos, tmp_path / "sweep", f"probes={probes}", "feature=dyaw")
    with pytest.raises(UsageError, match="no 'dx' probe for layer backbone.0"):
        sweep(demos, tmp_path / "sweep-dx", f"probes={probes}", "feature=dx")
    table = pd.read_parquet(out / "sweep.parquet")
    layers = tiny_policy("hybrid").layer_names()
    assert set(table["layer"]) == set(layers) and set(table["alpha"]) == {-3.0, 3.0}
    assert len(table) == len(layers) * 2 * 6
    assert {"d_dyaw", "d_gripper_action", "d_dx"} <= set(table.columns)
    # Pushing at an early backbone layer changes the actions; the hybrid's last backbone layer feeds nothing.
    early = table[table["layer"] == "backbone.0"][["d_dx", "d_dyaw"]].abs().to_numpy()
    assert early.max() > 1e-4
    last = table[table["layer"] == layers[len(layers) // 2 - 1]][["d_dx", "d_dyaw"]].abs().to_numpy()
    np.testing.assert_allclose(last, 0, atol=1e-6)
    norms = pd.read_parquet(out / "norms.parquet")
    assert set(norms["layer"]) == set(layers) and (norms["norm"] > 0).all()
    result = runner.invoke(app, ["plot", "sweep", f"run_dir={out}", "formats=[png]"])
    assert result.exit_code == 0, result.output
    assert (out / "figures" / "fig2_sweep.png").stat().st_size > 0


def test_zero_alpha_changes_nothing(demos, tmp_path):
    table = pd.read_parquet(sweep(demos, tmp_path / "sweep", "direction=random", "alphas=[0]") / "sweep.parquet")
    np.testing.assert_allclose(table.filter(like="d_").to_numpy(), 0, atol=1e-6)


def test_an_interrupted_sweep_resumes_from_its_finished_batches(demos, tmp_path, monkeypatch):
    from vlactl.steering import sweep as sweep_module

    whole = pd.read_parquet(sweep(demos, tmp_path / "whole", "direction=random") / "sweep.parquet")
    swept, run_batch = [], sweep_module._sweep_batch

    def stop_at_the_second(vla, obs, index, *rest):
        if swept:
            raise KeyboardInterrupt
        swept.append(list(index))
        return run_batch(vla, obs, index, *rest)

    monkeypatch.setattr(sweep_module, "_sweep_batch", stop_at_the_second)
    with pytest.raises(KeyboardInterrupt):
        sweep(demos, tmp_path / "resumed", "direction=random")
    assert not (tmp_path / "resumed" / "sweep.parquet").exists()
    monkeypatch.setattr(sweep_module, "_sweep_batch", lambda vla, obs, index, *rest: swept.append(list(index))
                        or run_batch(vla, obs, index, *rest))
    table = pd.read_parquet(sweep(demos, tmp_path / "resumed", "direction=random") / "sweep.parquet")
    assert len(swept) == 2 and swept[0] != swept[1]  # the first batch once, then only the second
    pd.testing.assert_frame_equal(table, whole)
    swept.clear()
    sweep(demos, tmp_path / "resumed", "direction=random", "seed=1")  # another direction: starts over
    assert len(swept) == 2


@pytest.mark.parametrize("extra, message", [
    (["direction=probe"], "needs probes="),
    (["direction=sideways"], "direction"),
    (["alphas=[]"], "alphas"),
    (["direction=ones", "layers=[backbone.7]"], "unknown layer 'backbone.7'"),
    (["probes=/nonexistent", "feature=dyaw"], "'/nonexistent' is not a probe run folder"),
])
def test_bad_input_is_a_usage_error(demos, tmp_path, extra, message):
    with pytest.raises(UsageError, match=message):
        sweep(demos, tmp_path / "sweep", *extra)
