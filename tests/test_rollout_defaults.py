"""What `vlactl rollout --constraint ...` finds by itself: the model, the method, the shipped probes, the constants
the constraints are stated in."""

import json

import pytest

from vlactl.errors import UsageError
from vlactl.rollout.plan import SHIPPED_PROBES, demo_constant, probes_run
from vlactl.rollout.runner import resolved_method, rollout_config, run_rollout


def test_a_constraint_alone_means_the_controller_on_the_embedded_hybrid():
    cfg = rollout_config(["constraint=height=high"])
    assert cfg.model == "hybrid" and resolved_method(cfg) == "control"
    assert resolved_method(rollout_config([])) == "none"
    assert resolved_method(rollout_config(["constraint=height=high", "method=prompt"])) == "prompt"


def test_a_model_without_shipped_probes_says_so():
    cfg = rollout_config(["model=random", "constraint=gripper=open", "method=control"])
    with pytest.raises(UsageError, match="needs probes=.*none ship for model 'random'"):
        probes_run(cfg)


def test_constants_come_from_the_probe_run_when_the_demonstrations_are_not_on_disk(tmp_path):
    run = tmp_path / "probes"
    run.mkdir()
    (run / "provenance.json").write_text(json.dumps({"speed_threshold": 0.21, "metres_per_unit": 0.0123}))
    cfg = rollout_config([f"demos={tmp_path / 'nowhere'}"])
    assert demo_constant(cfg, "metres_per_unit", run) == 0.0123
    assert demo_constant(cfg, "speed_threshold", run) == 0.21
    assert demo_constant(rollout_config(["metres_per_unit=0.02"]), "metres_per_unit", None) == 0.02
    with pytest.raises(UsageError, match="make it with `vlactl demos`"):
        demo_constant(cfg, "speed_threshold", tmp_path)
    # no probe run (none, prompt, filter): the shipped probes' record, so `--method filter` runs on a fresh clone
    shipped = json.loads((SHIPPED_PROBES / "hybrid" / "steer" / "provenance.json").read_text())
    assert demo_constant(cfg, "speed_threshold", None) == shipped["speed_threshold"]
    with pytest.raises(UsageError, match="make it with `vlactl demos`"):
        demo_constant(rollout_config([f"demos={tmp_path / 'nowhere'}", "model=random"]), "speed_threshold", None)


@pytest.mark.skipif(not (SHIPPED_PROBES / "hybrid" / "steer" / "metrics.parquet").is_file(), reason="no shipped probes")
def test_a_fresh_clone_steers_the_hybrid_with_its_shipped_probes(tmp_path):
    import pandas as pd

    summary = run_rollout(rollout_config(["constraint=height=high", "tasks=[0]", "episodes_per_task=1", "max_steps=6",
                                          "workers=1", f"output_root={tmp_path}", f"demos={tmp_path / 'none'}"]))
    assert summary["method"] == "control" and summary["model"] == "hybrid" and summary["steered_layers"]
    steps = pd.read_parquet(tmp_path / "hybrid_libero_spatial_height-high_control" / "steps.parquet")
    bounded = steps.dropna(subset=["bound_lo"])
    assert bounded["t"].tolist() == [0, 5]  # every re-plan in the window (the hybrid re-plans every 5 actions)
    assert bounded["bound_lo"].iloc[0] > 0  # at the start height, below its 1 cm margin: the barrier asks for a rise
