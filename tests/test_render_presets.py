"""Render presets: `env=fast` keeps the old defaults, `env=standard` renders LIBERO's own pixels and is the real
adapters' default, checkpoints record their render settings, and stages warn in one line when theirs differ."""

import contextlib
import io
import json
from dataclasses import asdict
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import fixture_policy
from vlactl.config import REPO_ROOT, load_config, load_policy_stage_config
from vlactl.env.libero_env import EnvConfig
from vlactl.render_presets import presets, warn_if_rendered_otherwise

FAST, STANDARD = presets()["fast"], presets()["standard"]


def test_fast_is_the_env_default_and_keeps_its_values():
    # Demo sets and their code fingerprints record these values: the fast preset must not change them.
    assert FAST == asdict(EnvConfig()) == {
        "image_size": 128, "settle_steps": 10, "reflections": False, "shadows": True, "skybox": True,
        "msaa_samples": 0, "cull_offscreen": True, "mesh_cell_mm": 2.0,
    }
    for stage in ("rollout", "demos"):
        assert load_config(stage).env == FAST
    assert load_config("demos", ["env=standard"]).env == STANDARD


def test_real_models_render_standard_unless_told_otherwise():
    def env(*overrides):
        return load_policy_stage_config("rollout", list(overrides)).env

    for model in ("pi05", "smolvla", "openvla"):
        assert env(f"model={model}", "model.checkpoint=somewhere") == STANDARD
    assert env("model=pi05", "env.image_size=224") == {**STANDARD, "image_size": 224}
    assert env("model=pi05", "env=fast") == FAST
    assert env("model=hybrid") == FAST == env("model=scripted")
    assert "env" not in load_policy_stage_config("collect", ["model=pi05"])  # stages that read datasets render nothing


def _checkpoint(folder: Path, env) -> Path:
    folder.mkdir(parents=True)
    (folder / "config.json").write_text("{}")
    (folder / "provenance.json").write_text(json.dumps({"env": env}))
    return folder


def _warning(*args, **kwargs) -> str:
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        warn_if_rendered_otherwise(*args, **kwargs)
    return err.getvalue()


def test_one_line_warning_when_the_run_renders_otherwise(tmp_path):
    ckpt = str(_checkpoint(tmp_path / "ckpt", FAST))
    line = _warning(ckpt, None, env=STANDARD)
    assert line == (
        f"warning: model {ckpt} was trained on env settings {{image_size: 128, reflections: false, msaa_samples: 0, "
        "mesh_cell_mm: 2.0}; this run uses {image_size: 256, reflections: true, msaa_samples: 4, mesh_cell_mm: 0.0} "
        "(env=fast renders as it was trained)\n"
    )
    assert _warning(ckpt, None, env={**FAST, "cull_offscreen": False, "settle_steps": 20}) == ""  # same pixels
    assert _warning(str(_checkpoint(tmp_path / "old", None)), None, env=STANDARD) == ""  # trained before the record
    assert _warning("random", None, env=STANDARD) == "" == _warning("scripted", None, env=STANDARD)

    real = SimpleNamespace(env_preset="standard")  # a real adapter: trained on LIBERO's renders
    assert _warning("pi05", real, env=STANDARD) == ""
    assert "(env=standard renders as it was trained)" in _warning("pi05", real, env=FAST)


def test_collect_and_sweep_warn_about_the_dataset(tmp_path):
    real = SimpleNamespace(env_preset="standard")
    demos = tmp_path / "demos_fast"
    (demos / "meta").mkdir(parents=True)
    (demos / "meta" / "vlactl_demos.json").write_text(json.dumps({"config": {"env": FAST}}))
    line = _warning("pi05", real, dataset=demos)
    assert line.startswith("warning: model pi05 was trained on env settings {image_size: 256, reflections: true,")
    assert "; dataset demos_fast was rendered with {image_size: 128," in line
    assert line.endswith("(vlactl demos env=standard renders as it was trained)\n") and line.count("\n") == 1
    assert _warning("pi05", real, dataset=tmp_path) == ""  # not a vlactl demo set: its settings are unknown


def test_shipped_checkpoints_record_the_fast_preset():
    for name in ("hybrid", "autoregressive"):
        provenance = json.loads((REPO_ROOT / "data" / "policies" / name / "provenance.json").read_text())
        assert provenance["env"] == FAST


def test_rollout_warns_at_its_start(tmp_path, capsys):
    from vlactl.rollout.runner import rollout_config, run_rollout

    ckpt = _checkpoint(tmp_path / "ckpt", FAST)
    cfg = rollout_config([f"model={ckpt}", "env=standard", "tasks=[0]", "episodes_per_task=0", "workers=1",
                          f"output_root={tmp_path / 'runs'}"])
    run_rollout(cfg, load_policy=fixture_policy.load)
    assert "trained on env settings {image_size: 128," in capsys.readouterr().err


def test_train_policy_records_the_datasets_render_settings(tmp_path):
    from synthetic_demos import write_synthetic_demos
    from test_train_policy import overrides

    from vlactl.training.train_policy import run_train_policy

    demos = write_synthetic_demos(tmp_path / "demos", episodes=2, frames=6)
    (demos / "meta" / "vlactl_demos.json").write_text(json.dumps({"config": {"env": FAST}}))
    ckpt = run_train_policy(load_config("train_policy", overrides(demos, tmp_path / "run", "hybrid", 1)))
    assert json.loads((ckpt / "provenance.json").read_text())["env"] == FAST


@pytest.mark.slow
def test_standard_renders_libero_s_own_pixels():
    """The same simulator state through the standard preset and through LIBERO's own OffScreenRenderEnv (robosuite's
    render path, MuJoCo's defaults) at the same size: the same pixels once LIBERO's upside-down images are flipped."""
    from libero.libero.envs import OffScreenRenderEnv

    from vlactl.env.libero_env import IMAGE_KEYS, LiberoEnv

    with LiberoEnv("libero_spatial", 0, EnvConfig(**STANDARD), render=True) as ours:
        ours.reset(0, seed=0)
        ours.env.step(np.array([0.4, -0.3, 0.2, 0, 0, 0, 1.0]))  # the arm moved, the fingers closing
        state = ours.env.sim.get_state().flatten()
        # Both envs render a forwarded state (after a step MuJoCo's poses lag its joint positions by one step).
        ours.env.set_init_state(state)
        mine = ours.render()
        with contextlib.redirect_stdout(io.StringIO()):
            libero = OffScreenRenderEnv(bddl_file_name=ours.task.bddl_file, camera_heights=STANDARD["image_size"],
                                        camera_widths=STANDARD["image_size"])
        try:
            libero.seed(0)
            np.random.seed(0)  # LIBERO places fixtures from NumPy's global RNG at reset, as LiberoEnv.reset does
            libero.reset()
            theirs = libero.set_init_state(state)
        finally:
            libero.close()
    for camera, key in IMAGE_KEYS.items():
        np.testing.assert_array_equal(theirs[f"{camera}_image"][::-1, ::-1], mine[key], err_msg=camera)
