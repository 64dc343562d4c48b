"""`vlactl demos` end to end on one task: a LeRobot v3 dataset with the documented keys, resumable."""

import json

import numpy as np
import pytest

from vlactl.config import load_config
from vlactl.data.demos import run_demos
from vlactl.data.lerobot_format import ACTION_KEY, IMAGE_KEY, ROBOT_STATE_KEY, STATE_KEY, WRIST_KEY


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("demos") / "spatial"
    base = ["suite=libero_spatial", "tasks=[0]", "workers=1", f"output_dir={out}"]
    first = run_demos(load_config("demos", base + ["episodes_per_task=1"]))
    second = run_demos(load_config("demos", base + ["episodes_per_task=2"]))  # resumes: runs only episode 1
    return out, first, second


def test_expert_succeeds_and_summary_counts(demo_run):
    out, first, second = demo_run
    assert first["attempted"] == 1 and second["attempted"] == 2
    assert second["succeeded"] == 2
    saved = json.loads((out / "meta" / "vlactl_demos.json").read_text())
    assert saved["per_task"]["0"]["succeeded"] == 2
    assert (out / "config.yaml").exists()


def test_resume_reuses_finished_episodes(demo_run):
    out, _, _ = demo_run
    staged = sorted((out.parent / "spatial.staging" / "task00").glob("*.npz"))
    assert [p.name for p in staged] == ["ep0000.npz", "ep0001.npz"]


def test_rerun_with_nothing_new_leaves_the_written_dataset_alone(demo_run, monkeypatch):
    """A re-run that adds no episode and finds the same summary skips the dataset writing; a missing summary (a write
    cut short before it) writes again."""
    import vlactl.data.lerobot_format as lerobot_format

    out, _, second = demo_run
    writes = []
    monkeypatch.setattr(lerobot_format, "write_dataset", lambda root, *args: writes.append(root))
    config = load_config("demos", ["suite=libero_spatial", "tasks=[0]", "workers=1", f"output_dir={out}",
                                   "episodes_per_task=2"])
    assert run_demos(config) == second and writes == []
    saved = (out / "meta" / "vlactl_demos.json").read_text()
    (out / "meta" / "vlactl_demos.json").unlink()
    run_demos(config)
    assert writes == [out] and (out / "meta" / "vlactl_demos.json").read_text() == saved


def test_dataset_has_documented_frames(demo_run):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    out, _, _ = demo_run
    ds = LeRobotDataset("vlactl/libero_spatial", root=out)
    assert ds.num_episodes == 2
    frame = ds[0]
    assert tuple(frame[IMAGE_KEY].shape) == (3, 128, 128) and tuple(frame[WRIST_KEY].shape) == (3, 128, 128)
    assert tuple(frame[STATE_KEY].shape) == (8,) and tuple(frame[ACTION_KEY].shape) == (7,)
    assert tuple(frame[ROBOT_STATE_KEY].shape) == (7,)
    assert frame["task"].startswith("pick up the black bowl")
    actions = np.stack([ds[i][ACTION_KEY].numpy() for i in range(0, ds.num_frames, 5)])
    assert np.all(np.abs(actions) <= 1.0)
    assert (actions[:, 6] > 0).any() and (actions[:, 6] < 0).any()  # the gripper opens and closes


RAISED_STEPS = 8


def _rollout_run(folder, episodes: int, actions: np.ndarray, first: int = 0):
    """A finished `vlactl rollout` run's two tables, as much of them as replaying reads: task 0's `episodes`
    episodes numbered from `first` (as `first_episode=` numbers them), each having executed `actions`."""
    import pandas as pd

    from vlactl.env.features import ACTION_FEATURES

    folder.mkdir(parents=True)
    numbers = range(first, first + episodes)
    pd.DataFrame({"suite": "libero_spatial", "task_id": 0, "episode": numbers, "init_state": numbers,
                  "seed": numbers, "start_gripper": "open"}).to_parquet(folder / "episodes.parquet")
    steps = [pd.DataFrame(actions, columns=list(ACTION_FEATURES)).assign(task_id=0, episode=k, t=range(len(actions)))
             for k in numbers]
    pd.concat(steps).to_parquet(folder / "steps.parquet")
    return folder


@pytest.fixture(scope="module")
def special_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("special") / "special"
    raised = np.tile([0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0], (RAISED_STEPS, 1))  # what a pushed policy did: go up
    run = _rollout_run(out.with_name("rollout"), 1, raised)
    summary = run_demos(load_config("demos", ["suite=libero_spatial", "tasks=[0]", "workers=1", f"output_dir={out}",
                                              "episodes_per_task=0", "recovery_episodes_per_task=1",
                                              "closed_start_episodes_per_task=1",
                                              "closed_approach_episodes_per_task=1",
                                              "noisy_episodes_per_task=1", "replayed_episodes_per_task=1",
                                              f"replay_from={run}", "replay_first=0"]))
    return out.with_name("special.staging") / "task00", summary


def test_recovery_demonstration_starts_after_a_missed_grasp(special_run):
    staged, summary = special_run
    assert summary["attempted"] == 0 and summary["recovery"]["succeeded"] == 1
    with np.load(staged / "rec0000.npz") as ep:
        aperture, grip = ep["robot_state"][:, 6], ep["action"][:, 6]
    assert aperture[0] < 0.08  # recorded from the lift of an empty, closed gripper
    opened = np.flatnonzero(grip < 0)
    assert opened.size and opened[0] < 10  # it opens at once ...
    assert (grip[opened[0]:] > 0).any()  # ... and grasps again


def test_closed_start_demonstration_labels_the_held_gripper_open(special_run):
    staged, summary = special_run
    assert summary["closed_start"]["succeeded"] == 1
    with np.load(staged / "cls0000.npz") as ep:
        aperture, grip = ep["robot_state"][:, 6], ep["action"][:, 6]
    assert aperture[0] < 0.3  # settled closed ...
    assert (grip[:5] < 0).all()  # ... while the recorded labels are the expert's: open
    assert (aperture > 0.8).any() and (grip > 0).any()  # it opens, then grasps


def test_closed_approach_demonstration_keeps_the_gripper_closed_until_over_the_grasp(special_run):
    staged, summary = special_run
    assert summary["closed_approach"]["succeeded"] == 1
    with np.load(staged / "cla0000.npz") as ep:
        aperture, grip, z = ep["robot_state"][:, 6], ep["action"][:, 6], ep["robot_state"][:, 2]
    opened = np.flatnonzero(grip < 0)
    assert aperture[0] < 0.3 and opened.size and opened[0] >= 5  # settled closed, labelled closed on the way
    assert (grip[:opened[0]] > 0).all()
    assert z[opened[0]] >= z[opened[0]:].min() + 0.03  # it opens above the grasp height, then goes down to grasp
    assert (grip[opened[0]:] > 0).any()


def _motion_explained_by_labels(path) -> float:
    """R^2 of a linear fit of the hand's per-step motion on the recorded x, y, z commands."""
    with np.load(path) as ep:
        motion, labels = np.diff(ep["robot_state"][:, :3], axis=0), ep["action"][:-1, :3]
    inputs = np.c_[labels, np.ones(len(labels))]
    resid = motion - inputs @ np.linalg.lstsq(inputs, motion, rcond=None)[0]
    return 1 - (resid**2).sum() / ((motion - motion.mean(0)) ** 2).sum()


def test_noisy_demonstration_executes_noise_but_records_the_expert(demo_run, special_run):
    staged, summary = special_run
    assert summary["noisy"]["succeeded"] == 1
    ordinary = demo_run[0].parent / "spatial.staging" / "task00" / "ep0000.npz"  # the same initial state
    # the executed noise moves the hand in ways its labels do not explain (0.85 against 0.91 measured)
    assert _motion_explained_by_labels(staged / "noi0000.npz") < _motion_explained_by_labels(ordinary) - 0.03


def test_replayed_demonstration_executes_the_run_then_records_the_expert(demo_run, special_run):
    staged, summary = special_run
    assert summary["replayed"]["succeeded"] == 1
    with np.load(staged / "rpl0000.npz") as ep:
        z, labels = ep["robot_state"][:, 2], ep["action"]
    with np.load(demo_run[0].parent / "spatial.staging" / "task00" / "ep0000.npz") as ep:  # the same start
        expert_z = ep["robot_state"][:, 2]
    assert z[RAISED_STEPS] - z[0] > 0.05  # the run's actions were executed: the hand went up ...
    assert expert_z[RAISED_STEPS] <= expert_z[0] + 0.01  # ... where the expert alone does not
    assert labels[:RAISED_STEPS, 2].max() < 0.5  # while the labels are the expert's own commands


def test_replays_are_refused_with_a_one_line_reason(tmp_path):
    from vlactl.data.demos import load_replays
    from vlactl.errors import UsageError

    with pytest.raises(UsageError, match="needs replay_from"):
        load_replays([], "libero_spatial", [0], 10, 1)
    with pytest.raises(UsageError, match="no episodes.parquet"):
        load_replays([str(tmp_path)], "libero_spatial", [0], 10, 1)
    run = _rollout_run(tmp_path / "run", 12, np.zeros((3, 7)))
    assert len(load_replays([str(run)], "libero_spatial", [0], 10, 2)) == 2
    with pytest.raises(UsageError, match="has 2 episodes of task 0 numbered 10 or later .* needs 3"):
        load_replays([str(run)], "libero_spatial", [0], 10, 3)
    with pytest.raises(UsageError, match="not suite=libero_object"):
        load_replays([str(run)], "libero_object", [0], 10, 1)
    assert load_replays([], "libero_spatial", [0], 10, 0) == {}


def test_several_runs_are_replayed_each_under_its_own_numbers(tmp_path):
    """replay_from=[a,b]: `count` episodes from each, b's numbered from REPLAY_STRIDE, so that a staging folder's
    replays of a keep their names whatever count b is given later."""
    from vlactl.data.demos import REPLAY_STRIDE, load_replays, replay_runs

    up, down = np.zeros((3, 7)), np.zeros((5, 7))
    up[:, 2], down[:, 2] = 1.0, -1.0
    a = _rollout_run(tmp_path / "a", 12, up)
    b = _rollout_run(tmp_path / "b", 12, down)
    assert replay_runs(None) == [] and replay_runs(str(a)) == [str(a)] and replay_runs([a, b]) == [str(a), str(b)]
    replays = load_replays([str(a), str(b)], "libero_spatial", [0], 10, 2)
    assert sorted(replays) == [(0, 0), (0, 1), (0, REPLAY_STRIDE), (0, REPLAY_STRIDE + 1)]
    assert (replays[0, 1].actions[:, 2] == 1).all() and len(replays[0, 1].actions) == 3
    assert (replays[0, REPLAY_STRIDE].actions[:, 2] == -1).all() and len(replays[0, REPLAY_STRIDE].actions) == 5
    assert replays[0, REPLAY_STRIDE + 1].init_state == 11  # replay_first + 1 of b
    later = _rollout_run(tmp_path / "later", 5, up, first=15)  # a run started at first_episode=15: its own 15, 16
    assert [replay.init_state for replay in load_replays([str(later)], "libero_spatial", [0], 10, 2).values()] \
        == [15, 16]


def test_staging_refuses_episodes_from_other_code(tmp_path):
    from vlactl.data.demos import CODE_NAME, code_fingerprint, staged_code
    from vlactl.errors import UsageError

    env = {"image_size": 128, "shadows": True}
    staging = tmp_path / "spatial.staging"
    (staging / "task00").mkdir(parents=True)
    assert staged_code(staging, env, adding=True) == code_fingerprint(env)  # empty: recorded
    (staging / "task00" / "ep0000.npz").write_bytes(b"")
    assert staged_code(staging, env, adding=True) == code_fingerprint(env)  # same code and settings: resumes
    with pytest.raises(UsageError, match=code_fingerprint(env)):  # other render settings: other pixels
        staged_code(staging, {**env, "image_size": 64}, adding=True)
    (staging / CODE_NAME).write_text(json.dumps({"code": "0123456789abcdef"}))
    with pytest.raises(UsageError, match="0123456789abcdef"):
        staged_code(staging, env, adding=True)
    assert staged_code(staging, env, adding=False) == "0123456789abcdef"  # rewriting the dataset alone is fine
    (staging / CODE_NAME).unlink()
    with pytest.raises(UsageError, match="unknown version"):
        staged_code(staging, env, adding=True)


def test_fingerprint_hashes_what_records_episodes_not_the_bookkeeping():
    """Editing how demos are scheduled or written must not orphan staged episodes; editing the recorder must."""
    from vlactl.data.demos import recorder_sources

    names = {path.relative_to(path.parents[1]).as_posix() for path in recorder_sources()}
    assert {"data/recording.py", "expert/scripted.py", "env/libero_env.py", "env/perturbations.py"} <= names
    assert not names & {"data/demos.py", "data/lerobot_format.py"}


def test_replays_extend_a_set_made_without_them_but_never_mix_two_runs(tmp_path):
    """The DAgger stage hard-links robust3's staged episodes and adds replays of a rollout run to them."""
    from vlactl.data.demos import CODE_NAME, REPLAYED, code_fingerprint, staged_code
    from vlactl.errors import UsageError

    env = {"image_size": 128}
    staging = tmp_path / "dagger.staging"
    (staging / "task00").mkdir(parents=True)
    (staging / "task00" / "ep0000.npz").write_bytes(b"")
    (staging / CODE_NAME).write_text(json.dumps({"code": code_fingerprint(env)}))  # the base set's record
    a, b = ["runs/a", 10], ["runs/b", 10]
    assert staged_code(staging, env, adding=True, replay=[a]) == code_fingerprint(env)
    assert json.loads((staging / CODE_NAME).read_text())["replay"] == [a]
    (staging / "task00" / f"{REPLAYED.prefix}0000.npz").write_bytes(b"")
    assert staged_code(staging, env, adding=True, replay=[a]) == code_fingerprint(env)  # resumes
    assert staged_code(staging, env, adding=True) == code_fingerprint(env)  # other kinds only: the record stays
    assert json.loads((staging / CODE_NAME).read_text())["replay"] == [a]
    for other in ([b], [["runs/a", 0]], [b, a]):
        with pytest.raises(UsageError, match=r"replayed from runs/a \(replay_first=10\), not from runs/"):
            staged_code(staging, env, adding=True, replay=other)
    assert staged_code(staging, env, adding=True, replay=[a, b]) == code_fingerprint(env)  # a run added after a
    assert json.loads((staging / CODE_NAME).read_text())["replay"] == [a, b]
    assert staged_code(staging, env, adding=True, replay=[a]) == code_fingerprint(env)  # a alone: b's stay recorded
    assert json.loads((staging / CODE_NAME).read_text())["replay"] == [a, b]
    (staging / "task00" / f"{REPLAYED.prefix}0000.npz").unlink()
    assert staged_code(staging, env, adding=True, replay=[b]) == code_fingerprint(env)  # none replayed yet: replaced
    assert json.loads((staging / CODE_NAME).read_text())["replay"] == [b]
    (staging / "task00" / f"{REPLAYED.prefix}0000.npz").write_bytes(b"")
    (staging / CODE_NAME).write_text(json.dumps({"code": code_fingerprint(env), "replay": a}))  # one run, as recorded
    assert staged_code(staging, env, adding=True, replay=[a, b]) == code_fingerprint(env)   # before lists
    with pytest.raises(UsageError, match="not from runs/b"):
        (staging / CODE_NAME).write_text(json.dumps({"code": code_fingerprint(env), "replay": a}))
        staged_code(staging, env, adding=True, replay=[b])
