"""A probe saved as safetensors reads back the same, and refuses to load against another model, width or pooling."""

import pytest
import torch

from vlactl.errors import UsageError
from vlactl.steering.probe_file import load_probe, save_probe
from vlactl.steering.probes import LOGISTIC, Probe


def _probe():
    return Probe(
        feature="gripper", kind=LOGISTIC, layer="backbone.3", model="hybrid-small", pooling="prefix",
        weight=torch.randn(8, dtype=torch.float64), bias=0.25, mean=torch.randn(8, dtype=torch.float64),
        std=torch.rand(8, dtype=torch.float64) + 0.5, positive="gripper < 0.5 (closed)", metrics={"accuracy": 0.9},
    )


def test_round_trip(tmp_path):
    probe = _probe()
    save_probe(probe, tmp_path / "p.safetensors")
    back = load_probe(tmp_path / "p.safetensors", model="hybrid-small", width=8, pooling="prefix")
    for key in ("feature", "kind", "layer", "model", "pooling", "bias", "positive", "metrics"):
        assert getattr(back, key) == getattr(probe, key)
    for key in ("weight", "mean", "std"):
        torch.testing.assert_close(getattr(back, key), getattr(probe, key))
    x = torch.randn(5, 8)
    torch.testing.assert_close(back.reading(x), probe.reading(x))
    torch.testing.assert_close(back.output(x), torch.sigmoid(probe.reading(x)))


@pytest.mark.parametrize("kw, needle", [
    ({"model": "autoregressive-small"}, "model 'hybrid-small'"),
    ({"width": 16}, "width 8"),
    ({"pooling": "last"}, "pooling 'prefix'"),
])
def test_refuses_another_model_width_or_pooling(tmp_path, kw, needle):
    save_probe(_probe(), tmp_path / "p.safetensors")
    with pytest.raises(UsageError, match=needle) as err:
        load_probe(tmp_path / "p.safetensors", **kw)
    assert "\n" not in str(err.value)


def test_missing_and_foreign_files(tmp_path):
    with pytest.raises(UsageError, match="no probe file"):
        load_probe(tmp_path / "none.safetensors")
    (tmp_path / "junk.safetensors").write_bytes(b"not a tensor file")
    with pytest.raises(UsageError, match="not a readable safetensors"):
        load_probe(tmp_path / "junk.safetensors")
    from safetensors.torch import save_file

    save_file({"w": torch.zeros(2)}, str(tmp_path / "other.safetensors"))
    with pytest.raises(UsageError, match="not a vlactl probe"):
        load_probe(tmp_path / "other.safetensors")
