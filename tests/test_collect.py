"""`vlactl collect` on a tiny synthetic LeRobot dataset with the random test model: what is stored, resume,
subsampling, layer choice, derived labels, and bad input."""

import json

import numpy as np
import pandas as pd
import pytest
import torch
from synthetic_demos import write_synthetic_demos

from vlactl.config import load_policy_stage_config
from vlactl.errors import UsageError
from vlactl.models.registry import tiny_policy
from vlactl.steering.activations import ActivationStore
from vlactl.steering.collect import frame_labels, pooled_activations, run_collect

EPISODES, FRAMES = 3, 12  # episode k has FRAMES + k frames


@pytest.fixture(scope="module")
def demos(tmp_path_factory):
    return write_synthetic_demos(tmp_path_factory.mktemp("demos") / "synthetic", EPISODES, FRAMES)


def collect(demos, out, *extra, load_policy=None):
    cfg = load_policy_stage_config("collect", [
        "model=random", f"dataset={demos}", f"output_dir={out}", f"cache_dir={out.parent / 'cache'}", "batch_size=8",
        "shard_size=16", "threads=1", *extra,
    ])
    return run_collect(cfg, load_policy=load_policy)


def test_stores_every_layer_and_the_labels_of_every_frame(demos, tmp_path):
    store = ActivationStore(collect(demos, tmp_path / "acts"))
    vla = tiny_policy("hybrid")
    n = sum(FRAMES + k for k in range(EPISODES))
    assert store.n_frames == n and store.layers == vla.layer_names() and store.model == "hybrid"
    labels = store.labels
    assert labels["episode"].tolist() == [k for k in range(EPISODES) for _ in range(FRAMES + k)]
    assert labels["frame_index"].tolist() == [t for k in range(EPISODES) for t in range(FRAMES + k)]
    assert labels["init_state"].tolist() == labels["episode"].tolist()  # the synthetic episode k starts at init k
    x = store.load(["backbone.0"])
    assert x.shape == (1, n, vla.layer_width("backbone.0")) and torch.isfinite(x).all()
    assert (tmp_path / "acts" / "config.yaml").is_file()


def test_stored_rows_equal_a_direct_capture(demos, tmp_path):
    """Batching whole episodes must not reorder or mix frames: row i is frame i's own representation."""
    store = ActivationStore(collect(demos, tmp_path / "acts", "dtype=float32"))
    from vlactl.data.frames import load_frames
    from vlactl.models.base import PolicyInput

    frames = load_frames(demos, ("image", "wrist_image"), tmp_path / "cache")
    rows = np.array([0, FRAMES + 3, len(frames) - 1])
    images = np.asarray(frames.images[rows])
    obs = PolicyInput({"image": images[:, 0], "wrist_image": images[:, 1]}, frames.state[rows],
                      [frames.tasks[t] for t in frames.task[rows]])
    direct = pooled_activations(tiny_policy("hybrid"), ["backbone.1", "expert.1"], "prefix", obs)
    for i, name in enumerate(["backbone.1", "expert.1"]):
        torch.testing.assert_close(store.load([name])[0, rows], torch.from_numpy(direct[name]), rtol=1e-4, atol=1e-5)


def test_the_action_set_reads_the_mean_over_the_written_tokens():
    """An autoregressive model's `action` reading: its prediction run, one position a forward, averaged."""
    from synthetic_demos import observation

    from vlactl.models.hooks import capture

    vla, obs = tiny_policy("autoregressive"), observation()
    with capture(vla, ["backbone.1"], "action") as seen:
        vla.predict_action_chunk(obs)
    pooled = pooled_activations(vla, ["backbone.1"], "action", obs)["backbone.1"]
    torch.testing.assert_close(torch.from_numpy(pooled), torch.stack(seen["backbone.1"]).mean(0))


def test_resume_skips_committed_episodes(demos, tmp_path):
    out = tmp_path / "acts"
    collect(demos, out, "max_episodes=1")
    calls = []

    def counting_policy(name):
        vla = tiny_policy("hybrid")
        encode = vla.encode
        vla.encode = lambda obs: (calls.append(len(obs.state)), encode(obs))[1]
        return vla

    collect(demos, out, load_policy=counting_policy)
    assert sum(calls) == sum(FRAMES + k for k in range(1, EPISODES))  # only the episodes not yet stored
    assert ActivationStore(out).labels["episode"].tolist() == sorted(ActivationStore(out).labels["episode"])


def test_subsampling_and_layer_choice(demos, tmp_path):
    store = ActivationStore(collect(demos, tmp_path / "acts", "every=4", "layers=[backbone.1]", "pooling=last"))
    assert store.layers == ["backbone.1"] and store.pooling == "last"
    assert set(store.labels["frame_index"] % 4) == {0}
    assert store.n_frames == sum(len(range(0, FRAMES + k, 4)) for k in range(EPISODES))


def test_labels_are_derived_for_datasets_without_the_robot_features(demos, tmp_path):
    """A plain LIBERO dataset has only the 8-D state: the features come from it, speed from the positions."""
    from vlactl.data.frames import load_frames
    from vlactl.env.features import robot_state_from_libero

    frames = load_frames(demos, ("image", "wrist_image"), tmp_path / "cache")
    info_path = demos / "meta" / "info.json"
    info = json.loads(info_path.read_text())
    stripped = {k: v for k, v in info["features"].items() if k not in ("observation.robot_state", "speed", "init_state")}
    info_path.write_text(json.dumps({**info, "features": stripped}))
    try:
        labels = frame_labels(demos, frames)
    finally:
        info_path.write_text(json.dumps(info))
    expected = robot_state_from_libero(frames.state)
    np.testing.assert_allclose(labels[["x", "y", "z", "gripper"]].to_numpy(), expected[:, [0, 1, 2, 6]], rtol=1e-5)
    first = labels[labels["episode"] == 0]
    step = np.linalg.norm(np.diff(first[["x", "y", "z"]].to_numpy(), axis=0), axis=1) / 0.05
    np.testing.assert_allclose(first["speed"].to_numpy()[:-1], step, rtol=1e-4)
    assert (labels["init_state"] == -1).all()


@pytest.mark.parametrize("extra, message", [
    (["layers=[backbone.9]"], "unknown layer 'backbone.9'"),
    (["pooling=middle"], "pooling"),
    (["dtype=int8"], "dtype"),
    (["every=0"], "every"),
    (["layers=[expert.0]", "pooling=image"], "no tokens in the read-out set 'image'"),
    (["layers=[backbone.0]", "pooling=action"], "no tokens in the read-out set 'action'"),
])
def test_bad_input_is_a_usage_error(demos, tmp_path, extra, message):
    with pytest.raises(UsageError, match=message):
        collect(demos, tmp_path / "acts", *extra)


def test_refuses_to_mix_datasets(demos, tmp_path):
    out = tmp_path / "acts"
    collect(demos, out, "max_episodes=1")
    other = write_synthetic_demos(tmp_path / "other", 2, 5, seed=1)
    with pytest.raises(UsageError, match="another dataset"):
        collect(other, out)
    assert pd.read_parquet(out / "labels.parquet")["episode"].tolist() == [0] * FRAMES


def test_image_cache_holds_the_dataset_images_and_reads_any_frames(demos, tmp_path, monkeypatch):
    import pyarrow.parquet as pq

    from vlactl.data import frames as frames_module
    from vlactl.data.frames import data_files, load_frames

    monkeypatch.setattr(frames_module, "IMAGE_BATCH", 5)  # the cache is built over several batches
    frames = load_frames(demos, ("image", "wrist_image"), tmp_path / "cache")
    table = pq.read_table(data_files(demos)[0], columns=["observation.images.wrist_image", "index"])
    rows = table["index"].to_numpy()
    stored = frames_module._decode(table["observation.images.wrist_image"].to_pylist())
    assert np.array_equal(np.asarray(frames.images[rows, 1]), stored)
    index = np.array([30, 2, 3, 17, 4, 2])  # unsorted, repeated, with gaps beyond READ_GAP
    assert np.array_equal(frames.images_at(index), np.asarray(frames.images[index]))


def test_resume_refuses_activations_of_other_weights(demos, tmp_path):
    checkpoint = tmp_path / "policy"
    checkpoint.mkdir()
    tiny_policy("hybrid", seed=0).save_pretrained(checkpoint)
    collect(demos, tmp_path / "acts", f"model={checkpoint}", "max_episodes=1")
    tiny_policy("hybrid", seed=1).save_pretrained(checkpoint)  # retrained under the same path
    with pytest.raises(UsageError, match="other weights"):
        collect(demos, tmp_path / "acts", f"model={checkpoint}")
