"""The steering runtime in the forward pass: readings land in the box, the log, baselines, hooks removed, errors."""

import pytest
import torch
from synthetic_demos import observation

from vlactl.errors import UsageError
from vlactl.models.hooks import capture
from vlactl.models.registry import tiny_policy
from vlactl.rollout.constrained import push_record
from vlactl.steering.probes import REGRESSION, Probe
from vlactl.steering.steer import Constraint, Steerer


def probe(vla, layer="backbone.1", feature="z", seed=0, **about):
    width = vla.layer_width(layer)
    g = torch.Generator().manual_seed(seed)
    fields = dict(feature=feature, kind=REGRESSION, layer=layer, model=vla.name, pooling="prefix",
                  weight=torch.randn(width, generator=g, dtype=torch.float64), bias=0.1,
                  mean=torch.zeros(width), std=torch.ones(width))
    return Probe(**{**fields, **about})


def readings(vla, p, obs):
    vla.reset()  # the same flow-matching noise every time
    with capture(vla, [p.layer]) as seen, torch.inference_mode():
        vla.predict_action_chunk(obs)
    return torch.cat([p.reading(x) for x in seen[p.layer]])


@pytest.mark.parametrize("name, layer", [("hybrid", "backbone.1"), ("hybrid", "expert.0"), ("autoregressive", "backbone.1")])
def test_controlled_readings_are_all_inside_the_box(name, layer):
    vla, obs = tiny_policy(name), observation(2)
    p = probe(vla, layer)
    free = readings(vla, p, obs)
    lo, hi = float(free.max()) + 1.0, float(free.max()) + 2.0  # a box none of the free readings is in
    vla.reset()
    with Steerer(vla, [Constraint(p, lo, hi)]) as steer, capture(vla, [layer]) as seen, torch.inference_mode():
        vla.predict_action_chunk(obs)
    steered = torch.cat([p.reading(x) for x in seen[layer]])  # what the layer really held after the intervention
    assert ((steered >= lo - 1e-4) & (steered <= hi + 1e-4)).all()
    assert len(steered) == len(free)  # every forward through the layer (each flow step on expert layers) steered
    assert all(row["active"] and lo - 1e-6 <= row["after"] <= hi + 1e-6 for row in steer.log)
    torch.testing.assert_close(torch.tensor([row["after"] for row in steer.log], dtype=torch.float64), steered.double(), atol=1e-4, rtol=0)
    torch.testing.assert_close(readings(vla, p, obs), free)  # hooks gone: the plain model again


def test_inside_the_box_nothing_changes():
    vla, obs = tiny_policy("hybrid"), observation(2)
    p = probe(vla)
    vla.reset()
    with torch.inference_mode():
        plain = vla.predict_action_chunk(obs)
    vla.reset()
    with Steerer(vla, [Constraint(p, -1e9, 1e9)]) as steer, torch.inference_mode():
        torch.testing.assert_close(vla.predict_action_chunk(obs), plain)
    assert not any(row["active"] for row in steer.log)


def test_several_boxes_on_one_layer_hold_at_once():
    vla, obs = tiny_policy("hybrid"), observation(2)
    a, b = probe(vla, seed=1), probe(vla, feature="x", seed=2)
    with Steerer(vla, [Constraint(a, 5.0, 6.0), Constraint(b, -6.0, -5.0)]) as steer, torch.inference_mode():
        vla.predict_action_chunk(obs)
    assert {row["feature"] for row in steer.log} == {"z", "x"}
    assert all(row["zmin"] - 1e-6 <= row["after"] <= row["zmax"] + 1e-6 for row in steer.log)


def test_a_held_reading_stays_where_it_was():
    vla, obs = tiny_policy("hybrid"), observation(2)
    a, held = probe(vla, seed=1), probe(vla, feature="x", seed=2)
    boxes = [Constraint(a, 5.0, 6.0), Constraint(held, -0.01, 0.01, relative=True)]
    with Steerer(vla, boxes) as steer, torch.inference_mode():
        vla.predict_action_chunk(obs)
    rows = [row for row in steer.log if row["feature"] == "x"]
    assert rows and all(abs(row["after"] - row["before"]) <= 0.01 + 1e-6 for row in rows)
    assert all(row["zmin"] - 1e-6 <= row["after"] <= row["zmax"] + 1e-6 for row in steer.log)
    assert any(row["active"] for row in steer.log)


def test_fixed_alpha_and_direction_push_by_the_same_amount_every_time():
    vla, obs = tiny_policy("hybrid"), observation(2)
    p = probe(vla)
    with Steerer(vla, [Constraint(p)], method="alpha", alpha=3.0) as steer, torch.inference_mode():
        vla.predict_action_chunk(obs)
    shift = torch.tensor([row["after"] - row["before"] for row in steer.log])
    torch.testing.assert_close(shift, torch.full_like(shift, 3.0 * float(p.weight.norm())), rtol=1e-4, atol=1e-4)
    d = torch.zeros(vla.layer_width(p.layer))
    d[0] = 1.0
    with Steerer(vla, [Constraint(p)], method="direction", alpha=2.0, directions={p.layer: d}) as steer:
        with torch.inference_mode():
            vla.predict_action_chunk(obs)
    assert all(row["u_norm"] == pytest.approx(2.0) for row in steer.log)


def test_probe_of_another_model_or_pooling_is_refused():
    vla = tiny_policy("hybrid")
    with pytest.raises(UsageError, match="trained on model 'autoregressive'"):
        Steerer(vla, [Constraint(probe(vla, model="autoregressive"))])
    with pytest.raises(UsageError, match="pooling 'last'"):
        Steerer(vla, [Constraint(probe(vla, pooling="last"))], pooling="prefix")
    with pytest.raises(UsageError, match="pooling 'last'"):  # probes of two read-out sets in one push
        Steerer(vla, [Constraint(probe(vla)), Constraint(probe(vla, layer="backbone.0", pooling="last"))])


def test_the_push_goes_where_the_probes_read():
    """A probe fitted at the `action` set is pushed there: on an autoregressive model, at every written token."""
    vla = tiny_policy("autoregressive")
    with Steerer(vla, [Constraint(probe(vla, pooling="action"), 1.0, 1.0)]) as steer:
        vla.predict_action_chunk(observation())
    assert steer.pooling == "action" and len(steer.log) == 2 * vla.chunk_size * 7  # a state feature: every token
    assert all(row["after"] == pytest.approx(1.0) for row in steer.log)
    # a feature of the action: only where its dimensions' tokens are written (dz the third of each action's seven)
    for feature, per_action in (("dz", 1), ("speed", 3)):
        with Steerer(vla, [Constraint(probe(vla, feature=feature, pooling="action"), 1.0, 1.0)]) as steer:
            vla.predict_action_chunk(observation())
        assert len(steer.log) == 2 * vla.chunk_size * per_action
    # a hold on dx is pushed where dx is written, before dz: the step table still reads the constraint's own probe
    dz, dx = probe(vla, feature="dz", pooling="action"), probe(vla, feature="dx", pooling="action", seed=1)
    with Steerer(vla, [Constraint(dz, 1.0, 1.0), Constraint(dx, 0.0, 0.0, relative=True)]) as steer:
        vla.predict_action_chunk(observation())
    assert [(e["box"], e["feature"]) for e in steer.log if e["row"] == 0][:2] == [(1, "dx"), (0, "dz")]
    assert push_record(steer.log)["reading_after"] == pytest.approx(1.0)
    with pytest.raises(UsageError, match="unknown steering method 'push'"):
        Steerer(vla, [Constraint(probe(vla))], method="push")
