"""Forward hooks: readings equal the masked mean, interventions shift that reading by exactly u, hooks go away."""

import pytest
import torch
from synthetic_demos import observation

from vlactl.models.hooks import capture, intervene, masked_mean
from vlactl.models.registry import MODELS, tiny_policy


def _hooks_left(policy) -> int:
    return sum(len(policy.layer_module(name)._forward_hooks) for name in policy.layer_names())


@pytest.mark.parametrize("name", list(MODELS))
def test_reading_is_the_masked_mean_of_the_layer_output(name):
    policy = tiny_policy(name)
    layer = "backbone.1"
    outputs = []
    handle = policy.layer_module(layer).register_forward_hook(lambda m, a, out: outputs.append(out))
    try:
        with capture(policy, [layer], pooling="text") as readings:
            policy.encode(observation())
    finally:
        handle.remove()
    mask = policy.token_mask(layer, "text")
    manual = (outputs[0] * mask[..., None]).sum(1) / mask.sum(1, keepdim=True)
    assert torch.allclose(readings[layer][0], manual, atol=1e-6)


@pytest.mark.parametrize("pooling", ["prefix", "image", "text", "last"])
def test_intervention_shifts_the_reading_by_exactly_u(pooling):
    policy = tiny_policy("hybrid")
    layer = "backbone.0"
    u = torch.randn(2, policy.layer_width(layer))
    seen = []

    def add_u(name, pooled):
        seen.append(pooled)
        return u

    with intervene(policy, [layer], add_u, pooling), capture(policy, [layer], pooling) as after:
        policy.encode(observation())
    assert torch.allclose(after[layer][0], seen[0] + u, atol=1e-5)


@pytest.mark.parametrize("name,layer", [("hybrid", "backbone.0"), ("hybrid", "expert.0"), ("autoregressive", "backbone.0")])
def test_intervention_changes_the_action_and_hooks_are_removed(name, layer):
    policy = tiny_policy(name)
    obs = observation()
    policy.reset()
    plain = policy.predict_action_chunk(obs)
    big = lambda _, pooled: torch.full_like(pooled, 5.0)  # noqa: E731
    policy.reset()
    with intervene(policy, [layer], big), capture(policy, policy.layer_names()):
        assert _hooks_left(policy) == len(policy.layer_names()) + 1
        steered = policy.predict_action_chunk(obs)
    assert not torch.allclose(plain, steered)
    assert _hooks_left(policy) == 0
    policy.reset()
    assert torch.equal(policy.predict_action_chunk(obs), plain)


@pytest.mark.parametrize("name", list(MODELS))
def test_steerable_layers_are_exactly_those_that_move_the_actions(name):
    policy = tiny_policy(name)
    obs = observation()

    def chunk(layer=None):
        policy.reset()
        with intervene(policy, [layer] if layer else [], lambda _, pooled: torch.full_like(pooled, 5.0)):
            return policy.predict_action_chunk(obs)

    plain = chunk()
    moved = [layer for layer in policy.layer_names() if not torch.equal(chunk(layer), plain)]
    assert moved == policy.steerable_layers()
    if name == "hybrid":  # the expert reads each backbone layer's keys/values: the last one's output feeds nothing
        assert "backbone.1" not in moved


def test_hooks_are_removed_on_error():
    policy = tiny_policy("hybrid")
    with pytest.raises(RuntimeError):
        with capture(policy, policy.layer_names()):
            raise RuntimeError("boom")
    assert _hooks_left(policy) == 0


def test_none_leaves_the_layer_alone_and_empty_sets_are_skipped():
    policy = tiny_policy("autoregressive")
    obs = observation()
    calls = []
    plain = policy.predict_action_chunk(obs)
    with intervene(policy, ["backbone.0"], lambda name, pooled: calls.append(pooled) or None):
        same = policy.predict_action_chunk(obs)
    assert torch.equal(plain, same)
    assert len(calls) == 1  # the prompt only: decode steps hold no prompt token


def test_masked_mean_ignores_masked_tokens():
    hidden = torch.tensor([[[1.0], [3.0], [100.0]]])
    assert masked_mean(hidden, torch.tensor([[True, True, False]])).item() == 2.0


def test_the_action_set_is_every_position_that_writes_an_action_token():
    """Autoregressive: the prompt's last token (it writes the first action token), then each decode step; a hybrid's
    is its action expert's tokens and nothing in the backbone."""
    policy = tiny_policy("autoregressive")
    with capture(policy, ["backbone.0"], "action") as action, capture(policy, ["backbone.0"], "last") as last:
        policy.encode_for(observation(), "action")
    assert len(action["backbone.0"]) == policy.chunk_size * 7 and len(last["backbone.0"]) == 1
    assert torch.equal(action["backbone.0"][0], last["backbone.0"][0])
    with capture(policy, ["backbone.0"], "action") as prompt_only:
        policy.encode_for(observation(), "prefix")
    assert len(prompt_only["backbone.0"]) == 1

    hybrid = tiny_policy("hybrid")
    with capture(hybrid, ["backbone.0", "expert.0"], "action") as action, \
            capture(hybrid, ["expert.0"], "prefix") as suffix:
        hybrid.encode_for(observation(), "action")
    assert action["backbone.0"] == [] and torch.equal(action["expert.0"][0], suffix["expert.0"][0])


def test_a_push_at_the_action_set_is_added_at_every_written_token():
    policy = tiny_policy("autoregressive")
    obs = observation()
    plain = policy.predict_action_chunk(obs)
    pushed = []

    def push(name, pooled):
        pushed.append(pooled.shape)
        return torch.full_like(pooled, 5.0)

    with intervene(policy, ["backbone.0"], push, "action"):
        steered = policy.predict_action_chunk(obs)
    assert pushed == [(2, policy.layer_width("backbone.0"))] * (policy.chunk_size * 7)
    assert not torch.equal(plain, steered)
    written = []
    with intervene(policy, ["backbone.0"], lambda name, pooled: written.append(policy.written_dimension()), "action"):
        policy.predict_action_chunk(obs)
    assert written == list(range(7)) * policy.chunk_size  # dx, dy, dz, droll, dpitch, dyaw, gripper, then again
