"""The activation store: what is written is read back, writes resume, and nothing half-written is ever read."""

import json

import numpy as np
import pandas as pd
import pytest
from synthetic_activations import write_store

from vlactl.errors import UsageError
from vlactl.steering.activations import LABEL_COLUMNS, ActivationStore, ActivationWriter
from vlactl.steering.synthetic import planted_activations, spec_labels


def test_round_trip(tmp_path):
    data = write_store(tmp_path / "acts", dtype="float32")
    store = ActivationStore(tmp_path / "acts")
    assert store.n_frames == len(data.episodes) and store.layers == [f"backbone.{i}" for i in range(4)]
    np.testing.assert_array_equal(store.load().numpy(), data.x)
    np.testing.assert_array_equal(store.load(["backbone.2", "backbone.0"]).numpy(), data.x[[2, 0]])
    labels = store.labels
    assert list(labels.columns[: len(LABEL_COLUMNS)]) == list(LABEL_COLUMNS)
    np.testing.assert_array_equal(labels["episode"].to_numpy(), data.episodes)
    meta = json.loads((tmp_path / "acts" / "meta.json").read_text())
    assert sum(meta["shards"]) == meta["n_frames"] and all(s >= 100 for s in meta["shards"][:-1])


def test_float16_store_is_close_and_loads_as_float32(tmp_path):
    data = write_store(tmp_path / "acts")
    x = ActivationStore(tmp_path / "acts").load()
    assert x.dtype.is_floating_point and x.element_size() == 4
    np.testing.assert_allclose(x.numpy(), data.x, rtol=1e-3, atol=1e-2)


def _open(folder, **kw):
    layers = ["a", "b"]
    args = dict(model="m", layers=layers, widths={"a": 3, "b": 3}, pooling="prefix", dtype="float32", shard_size=10)
    return ActivationWriter(folder, **{**args, **kw})


def _labels(episode, n):
    data = planted_activations(1, 1, n, 2, 15, seed=episode)
    df = spec_labels(data.latent, data.episodes)
    return df.assign(episode=episode)


def test_resume_appends_after_the_last_commit_and_ignores_anything_past_it(tmp_path):
    folder = tmp_path / "acts"
    with _open(folder) as w:
        w.append({"a": np.ones((12, 3)), "b": np.ones((12, 3))}, _labels(0, 12))  # 12 >= shard_size: committed
    # a crash after writing the next shard's files and labels but before meta.json: past the commit point
    np.save(folder / "layers" / "a" / "shard_00001.npy", np.full((5, 3), 7.0))
    pd.concat([_labels(0, 12), _labels(1, 5)]).to_parquet(folder / "labels.parquet")
    assert ActivationStore(folder).n_frames == 12 and len(ActivationStore(folder).labels) == 12
    w = _open(folder)
    assert w.n_frames == 12 and w.episodes() == {0}
    w.append({"a": np.full((4, 3), 2.0), "b": np.full((4, 3), 2.0)}, _labels(2, 4))
    w.close()
    store = ActivationStore(folder)
    assert store.n_frames == 16
    np.testing.assert_array_equal(store.load(["a"])[0, 12:].numpy(), np.full((4, 3), 2.0))
    assert store.labels["episode"].tolist() == [0] * 12 + [2] * 4


def test_buffered_frames_are_not_visible_before_a_flush(tmp_path):
    w = _open(tmp_path / "acts")
    w.append({"a": np.ones((3, 3)), "b": np.ones((3, 3))}, _labels(0, 3))
    assert ActivationStore(tmp_path / "acts").n_frames == 0
    w.flush()
    assert ActivationStore(tmp_path / "acts").n_frames == 3


def test_reopening_with_other_settings_is_refused(tmp_path):
    _open(tmp_path / "acts").close()
    with pytest.raises(UsageError, match="model='m'|model"):
        _open(tmp_path / "acts", model="other")
    with pytest.raises(UsageError, match="widths"):
        _open(tmp_path / "acts", widths={"a": 4, "b": 3})


def test_bad_appends_and_folders(tmp_path):
    w = _open(tmp_path / "acts", dtype="float16")
    with pytest.raises(ValueError, match="shape"):
        w.append({"a": np.ones((3, 4)), "b": np.ones((3, 3))}, _labels(0, 3))
    with pytest.raises(ValueError, match="float32"):
        w.append({"a": np.full((3, 3), 1e6), "b": np.ones((3, 3))}, _labels(0, 3))
    with pytest.raises(ValueError, match="lack columns"):
        w.append({"a": np.ones((3, 3)), "b": np.ones((3, 3))}, _labels(0, 3).drop(columns="speed"))
    with pytest.raises(UsageError, match="not an activation folder"):
        ActivationStore(tmp_path / "nowhere")
    with pytest.raises(UsageError, match="unknown layer"):
        ActivationStore(tmp_path / "acts").load(["c"])
