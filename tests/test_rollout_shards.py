"""`vlactl rollout shard=i num_shards=n` and the merge: two shards merged equal the run in one process row for row,
also after a shard is interrupted and resumed; no episode is lost or run twice; bad shard settings fail in one line.

With the registry's tiny random VLA (rendered images, the real model path), 3 episodes of 3 steps."""

import json
import shutil

import pandas as pd
import pytest

from test_cli import run
from vlactl.errors import UsageError
from vlactl.rollout import parts, shards
from vlactl.rollout.runner import SAME_RUN_KEYS, rollout_config, run_rollout

BASE = ["model=random", "tasks=[0]", "episodes_per_task=3", "max_steps=3", "workers=1"]
KEYS = [(0, 0), (0, 1), (0, 2)]


def _cfg(root, *extra):
    return rollout_config([*BASE, f"output_root={root}", *extra])


def _rows(folder):
    return pd.read_parquet(folder / "episodes.parquet").drop(columns="wall_s")


@pytest.fixture(scope="module")
def sharded(tmp_path_factory):
    """The whole run in one process, then shard 0 of 2, killed before its second episode was saved (its step table
    written, not its row: the state a kill leaves), shard 1 (not merged: shard 0 lacks one), and shard 0 resumed.
    The shards also write videos (not a setting of the run)."""
    root = tmp_path_factory.mktemp("shards")
    whole = run_rollout(_cfg(root, "run_name=whole"))
    out = root / "sharded"
    run_rollout(_cfg(root, "run_name=sharded", "shard=0", "num_shards=2", "video=true"))
    first = out / "shards" / "0-of-2"
    parts.stem(first, 0, 2).with_suffix(".json").unlink()
    kept = parts.stem(first, 0, 0).with_suffix(".parquet").stat().st_mtime_ns
    run_rollout(_cfg(root, "run_name=sharded", "shard=1", "num_shards=2", "video=true"))
    unmerged = not (out / "episodes.parquet").exists()
    merge = run("rollout", "merge", *BASE, f"output_root={root}", "run_name=sharded")
    resumed = run_rollout(_cfg(root, "run_name=sharded", "shard=0", "num_shards=2", "video=true"))
    return root, whole, out, unmerged, merge, kept, resumed


def test_slices_partition_the_run():
    keys = [(t, k) for t in (3, 0, 5) for k in range(7)]
    for n in (1, 2, 3, 8, 30):
        cut = [shards.slice_of(keys, i, n) for i in range(n)]
        assert sorted(key for piece in cut for key in piece) == sorted(keys)  # none lost, none twice
        assert cut == [shards.slice_of(list(reversed(keys)), i, n) for i in range(n)]  # the keys alone decide
    assert shards.slice_of(KEYS, 0, 2) == [(0, 0), (0, 2)] and shards.slice_of(KEYS, 1, 2) == [(0, 1)]
    assert "shard" not in SAME_RUN_KEYS and "num_shards" not in SAME_RUN_KEYS


def test_merge_waits_for_every_episode(sharded):
    _, _, out, unmerged, merge, _, _ = sharded
    assert unmerged  # shard 1 finished last but shard 0 lacked an episode: no run tables
    assert merge.returncode == 2, merge.stderr
    lines = [line for line in merge.stderr.splitlines() if line.strip() and "robosuite" not in line]
    assert len(lines) == 1 and "lacks 1 of 3 episodes" in lines[0] and "0:2" in lines[0], merge.stderr
    assert "shard 0-of-2" in lines[0]


def test_two_shards_merge_to_the_whole_run(sharded):
    root, whole, out, _, _, kept, resumed = sharded
    assert resumed["episodes"] == 2  # the shard's own summary: its slice
    assert parts.stem(out / "shards" / "0-of-2", 0, 0).with_suffix(".parquet").stat().st_mtime_ns == kept
    one = root / "whole"
    pd.testing.assert_frame_equal(_rows(out), _rows(one))
    pd.testing.assert_frame_equal(pd.read_parquet(out / "steps.parquet"), pd.read_parquet(one / "steps.parquet"))
    assert json.loads((out / "summary.json").read_text()) == json.loads((one / "summary.json").read_text())
    assert json.loads((out / "summary.json").read_text())["episodes"] == whole["episodes"] == 3
    assert all(parts.is_done(out, *key) for key in KEYS)  # the run folder resumes and serves judge_from as one run
    ran = [tuple(key) for i in (0, 1) for key in _rows(out / "shards" / f"{i}-of-2")[parts.EPISODE_KEY].values]
    assert sorted(ran) == KEYS  # each episode ran in exactly one shard
    assert sorted(p.name for p in (out / "videos").iterdir()) == [f"task00_ep000{k}.mp4" for k in range(3)]


def test_whole_run_takes_over_the_shards(sharded):
    """A run without shard= in a folder of finished shards runs nothing: its rows are theirs, wall_s included."""
    root, _, out, *_ = sharded
    shutil.copytree(out / "shards", root / "adopted" / "shards")
    assert run_rollout(_cfg(root, "run_name=adopted"))["episodes"] == 3
    pd.testing.assert_frame_equal(pd.read_parquet(root / "adopted" / "episodes.parquet"),
                                  pd.read_parquet(out / "episodes.parquet"))


def test_shard_with_other_settings_is_refused(sharded):
    root, *_ = sharded
    with pytest.raises(UsageError, match="seed"):
        run_rollout(_cfg(root, "run_name=sharded", "shard=1", "num_shards=2", "seed=5"))


@pytest.mark.parametrize(
    "args, needle",
    [(["shard=2", "num_shards=2"], "shard must be"), (["shard=-1", "num_shards=2"], "shard must be"),
     (["num_shards=0"], "num_shards must be")],
)
def test_bad_shard_is_one_line_and_exit_2(args, needle, tmp_path):
    res = run("rollout", *BASE, f"output_root={tmp_path}", *args)
    assert res.returncode == 2, res.stderr
    lines = [line for line in res.stderr.splitlines() if line.strip() and "robosuite" not in line]
    assert len(lines) == 1 and lines[0].startswith("error:") and needle in lines[0], res.stderr
    assert not list(tmp_path.iterdir())  # refused before the run folder, let alone a worker
