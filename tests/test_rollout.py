"""`vlactl rollout` end to end on one task with a fixture policy: tables, summary, resume, bad input.

Slow: the expert solves a task; a registry model gets rendered images and a video."""

import json

import imageio.v3 as iio
import numpy as np
import pandas as pd
import pytest

import fixture_policy
from test_cli import run
from vlactl.errors import UsageError
from vlactl.rollout import parts
from vlactl.rollout.runner import rollout_config, run_rollout


def _cfg(root, *extra):
    base = ["model=fixture", "tasks=[0]", "max_steps=4", "workers=1", f"output_root={root}"]
    return rollout_config(base + list(extra))


@pytest.fixture(scope="module")
def rollout(tmp_path_factory):
    root = tmp_path_factory.mktemp("rollout")
    first = run_rollout(_cfg(root, "episodes_per_task=1"), load_policy=fixture_policy.load)
    out = root / "fixture_libero_spatial"
    first_part = parts.stem(out, 0, 0).with_suffix(".parquet").stat().st_mtime_ns
    second = run_rollout(_cfg(root, "episodes_per_task=2"), load_policy=fixture_policy.load)  # resumes: runs ep 1
    return root, out, first, second, first_part


def test_tables_and_summary(rollout):
    _, out, _, second, _ = rollout
    episodes = pd.read_parquet(out / "episodes.parquet")
    assert list(episodes.columns) == parts.EPISODE_COLUMNS
    assert episodes[["task_id", "episode", "init_state", "seed"]].values.tolist() == [[0, 0, 0, 0], [0, 1, 1, 1]]
    assert (episodes["steps"] == 4).all() and not episodes["success"].any() and (episodes["method"] == "none").all()
    steps = pd.read_parquet(out / "steps.parquet")
    assert list(steps.columns) == parts.STEP_COLUMNS and len(steps) == 8
    assert np.allclose(steps["dz"], 0.3) and (steps["z"].diff()[steps["t"] > 0] > 0).all()  # it rises, as told
    bowl = steps.groupby("episode")[parts.OBJECT_COLUMNS]  # task 0 moves a bowl on the table; rising leaves it be
    assert bowl.count().eq(4).all().all() and (bowl.max() - bowl.min()).max().max() < 1e-3
    assert steps["object_z"].between(0.85, 0.95).all()
    saved = json.loads((out / "summary.json").read_text())
    assert saved == json.loads(json.dumps(second))
    assert saved["episodes"] == 2 and saved["per_task"]["0"]["successes"] == 0
    assert saved["policy"] == {"needs_images": False, "chunk_size": 4, "replan_every": 2, "gripper_levels": None}
    assert (out / "config.yaml").exists() and not (out / "videos").exists()


def test_resume_skips_finished_episodes(rollout):
    _, out, first, _, first_part = rollout
    assert first["episodes"] == 1
    assert parts.stem(out, 0, 0).with_suffix(".parquet").stat().st_mtime_ns == first_part


def test_resume_refuses_other_settings(rollout):
    root, *_ = rollout
    with pytest.raises(UsageError, match="seed"):
        run_rollout(_cfg(root, "episodes_per_task=2", "seed=5"), load_policy=fixture_policy.load)
    with pytest.raises(UsageError, match="episode_noise=True, not False"):
        run_rollout(_cfg(root, "episodes_per_task=2", "episode_noise=false"), load_policy=fixture_policy.load)


def test_first_episode_starts_the_run_further_on(tmp_path):
    """Episodes 1.. only: their own init states and seeds, as the same episodes of a run from 0 would have."""
    run_rollout(_cfg(tmp_path, "episodes_per_task=1", "first_episode=1"), load_policy=fixture_policy.load)
    episodes = pd.read_parquet(tmp_path / "fixture_libero_spatial" / "episodes.parquet")
    assert episodes[["task_id", "episode", "init_state", "seed"]].values.tolist() == [[0, 1, 1, 1]]


def test_runs_saved_before_episode_noise_resume_only_without_it(tmp_path):
    """Their episodes all restarted the model's one noise sequence: parts of both kinds must not mix."""
    from vlactl.rollout.runner import _differing_key

    saved = tmp_path / "config.yaml"
    saved.write_text("model: hybrid\n")
    assert _differing_key(saved, {"episode_noise": True}, ["episode_noise"]) == ("episode_noise", False, True)
    assert _differing_key(saved, {"episode_noise": False}, ["episode_noise"]) is None


def test_a_run_records_its_models_inference_options_and_resumes_only_with_them(tmp_path):
    """A checkpoint's own `samples` changed since a run began, or `model.samples=` given: the parts would mix."""
    from vlactl.models.registry import RANDOM, inference_options, tiny_policy
    from vlactl.rollout.runner import _differing_key

    tiny_policy("hybrid").save_pretrained(tmp_path)
    assert inference_options(str(tmp_path)) == {"samples": 1, "noise_scale": 1.0}
    five = inference_options(str(tmp_path), samples=5)
    assert five == {"samples": 5, "noise_scale": 1.0} and inference_options(RANDOM) is None
    saved = tmp_path / "config.yaml"
    saved.write_text("model: hybrid\nmodel_inference: {samples: 1, noise_scale: 1.0}\n")
    assert _differing_key(saved, {"model_inference": five}, ["model_inference"])[0] == "model_inference"
    saved.write_text("model: hybrid\n")  # a run saved before the key: not compared
    assert _differing_key(saved, {"model_inference": five}, ["model_inference"]) is None


@pytest.mark.parametrize(
    "args, needle",
    [
        (["model=scripted", "suite=libero_nope"], "libero_nope"),
        (["model=scripted", "--episodes-per-task", "-1"], "episodes_per_task"),
        (["model=no_such_model"], "no_such_model"),
        (["model=scripted", "first_episode=-3"], "first_episode"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(args, needle, tmp_path):
    res = run("rollout", f"output_root={tmp_path}", *args)
    assert res.returncode == 2, res.stderr
    lines = [line for line in res.stderr.splitlines() if line.strip() and "robosuite" not in line]
    assert len(lines) == 1 and lines[0].startswith("error:") and needle in lines[0], res.stderr


@pytest.mark.slow
def test_expert_succeeds(tmp_path):
    cfg = rollout_config(["model=scripted", "tasks=[0]", "episodes_per_task=1", "workers=1", f"output_root={tmp_path}"])
    assert run_rollout(cfg)["successes"] == 1


@pytest.mark.slow
def test_registry_model_with_images_and_video(tmp_path):
    """The registry's tiny random VLA needs images: they are rendered, fed to it, and written as a video."""
    cfg = rollout_config(["model=random", "tasks=[0]", "episodes_per_task=1", "workers=1", "max_steps=3", "video=true",
                          f"output_root={tmp_path}"])
    summary = run_rollout(cfg)
    assert summary["policy"]["needs_images"] and summary["episodes"] == 1
    video = iio.imread(tmp_path / "random_libero_spatial" / "videos" / "task00_ep0000.mp4", plugin="pyav")
    assert video.shape == (4, 128, 256, 3)  # the reset observation and one per step; agent view | wrist


def test_temporal_ensemble_averages_every_chunk_covering_a_step():
    """ensemble=0 (uniform weights): step t executes the mean of what chunks t-2..t predicted for it."""
    from types import SimpleNamespace

    import torch

    from vlactl.rollout.agents import VLAAgent

    class Counting:  # the n-th chunk (from 1) predicts n + 10 i for its i-th action
        chunk_size = replan_every = 3
        needs_images, gripper_levels = False, None

        def eval(self):
            return self

        def reset(self, seed):
            self.n = 0

        def predict_action_chunk(self, batch):
            self.n += 1
            return torch.tensor([[[self.n + 10.0 * i] * 7 for i in range(3)]])

    agent = VLAAgent(Counting(), snap_gripper=False, ensemble=0.0)
    obs = SimpleNamespace(images={}, libero_state=np.zeros(8))
    agent.reset(SimpleNamespace(instruction="x"), obs)
    executed = [agent.act(obs)[0] for _ in range(4)]
    assert executed == pytest.approx([1, (11 + 2) / 2, (21 + 12 + 3) / 3, (22 + 13 + 4) / 3])
    assert agent.replan_every == 1
    with pytest.raises(UsageError, match="replan_every=2"):
        VLAAgent(Counting(), replan_every=2, ensemble=0.01)


@pytest.mark.parametrize("args, needle", [
    (["constraint=gripper=open", "method=control"], "method none, prompt or filter"),
    (["model=scripted"], "model=scripted"),
    (["ensemble=abc"], "ensemble must be a number"),
])
def test_ensemble_bad_input(args, needle, tmp_path):
    with pytest.raises(UsageError, match=needle):
        run_rollout(_cfg(tmp_path, "ensemble=0.01", *args), load_policy=fixture_policy.load)
