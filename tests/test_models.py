"""The embedded models behind the VLA interface: shapes, ranges, layers, read-out masks, checkpoints, registry."""

import dataclasses

import pytest
import torch
from omegaconf import OmegaConf
from synthetic_demos import observation

from vlactl.config import CONF_DIR
from vlactl.errors import UsageError
from vlactl.models.registry import MODELS, RANDOM, load_policy, policy_class, tiny_policy


@pytest.mark.parametrize("name", list(MODELS))
def test_chunk_shape_and_range(name):
    policy = tiny_policy(name)
    chunk = policy.predict_action_chunk(observation())
    assert chunk.shape == (2, policy.chunk_size, 7)
    assert chunk.abs().max() <= 1.0 and torch.isfinite(chunk).all()
    assert 1 <= policy.replan_every <= policy.chunk_size


def test_layer_names_and_widths():
    hybrid, ar = tiny_policy("hybrid"), tiny_policy("autoregressive")
    assert hybrid.layer_names() == ["backbone.0", "backbone.1", "expert.0", "expert.1"]
    assert ar.layer_names() == ["backbone.0", "backbone.1"]
    assert hybrid.layer_width("backbone.0") == hybrid.config.width
    assert hybrid.layer_width("expert.1") == hybrid.config.expert_width
    with pytest.raises(KeyError):
        hybrid.layer_module("expert.2")


@pytest.mark.parametrize("name", list(MODELS))
def test_prefix_masks_count_tokens(name):
    policy = tiny_policy(name)
    cfg = policy.config
    obs = observation()
    policy.encode(obs)
    n_image = len(cfg.cameras) * cfg.image_tokens_side**2
    words = [len(text.split()) for text in obs.instruction]
    counts = {p: policy.token_mask("backbone.0", p).sum(1).tolist() for p in ("prefix", "image", "text", "last")}
    assert counts["prefix"] == [cfg.prefix_tokens()] * 2
    assert counts["image"] == [n_image] * 2
    assert counts["text"] == [min(w, cfg.max_text_tokens) for w in words]
    assert counts["last"] == [1, 1]
    assert policy.token_mask("backbone.1", "last")[:, -1].all()  # the state token closes the prompt


def test_expert_masks_are_the_action_tokens():
    policy = tiny_policy("hybrid")
    policy.encode(observation())
    assert policy.token_mask("expert.0", "prefix").sum(1).tolist() == [policy.chunk_size] * 2
    assert policy.token_mask("expert.0", "image").sum() == 0


def test_autoregressive_decode_steps_hold_no_prompt_token():
    policy = tiny_policy("autoregressive")
    policy.predict_action_chunk(observation())
    for pooling in ("prefix", "image", "text", "last"):
        assert not policy.token_mask("backbone.0", pooling).any()
    assert policy.token_mask("backbone.0", "action").all()  # each one writes the next action token


@pytest.mark.parametrize("name", list(MODELS))
def test_checkpoint_round_trip(name, tmp_path):
    policy = tiny_policy(name, seed=3)
    policy.save_pretrained(tmp_path)
    loaded = load_policy(str(tmp_path))
    assert type(loaded) is type(policy) and loaded.config == policy.config
    obs = observation()
    policy.reset(), loaded.reset()
    assert torch.equal(policy.predict_action_chunk(obs), loaded.predict_action_chunk(obs))


def test_hybrid_sampling_is_reproducible_after_reset():
    policy = tiny_policy("hybrid")
    obs = observation()
    first = policy.predict_action_chunk(obs)
    assert not torch.equal(first, policy.predict_action_chunk(obs))  # fresh noise within an episode
    policy.reset()
    assert torch.equal(first, policy.predict_action_chunk(obs))


def test_hybrid_episode_seed_gives_each_episode_its_own_noise():
    policy = tiny_policy("hybrid")
    obs = observation()

    def first_chunk(seed):
        policy.reset(seed)
        return policy.predict_action_chunk(obs)

    assert torch.equal(first_chunk(5), first_chunk(5))  # the same episode draws the same noise in every run
    assert not torch.equal(first_chunk(5), first_chunk(6))
    assert not torch.equal(first_chunk(5), first_chunk(None))
    assert torch.equal(first_chunk(None), first_chunk(None))  # no episode seed: the model's one sequence


def test_hybrid_samples_execute_the_median_of_independent_flows():
    """samples=3 draws three noises per row and flows each: the same flows as a batch of each row three times."""
    import numpy as np

    from vlactl.models.base import PolicyInput

    obs = observation()
    repeated = PolicyInput({k: np.repeat(v, 3, axis=0) for k, v in obs.images.items()}, np.repeat(obs.state, 3, axis=0),
                           [text for text in obs.instruction for _ in range(3)])
    flows = tiny_policy("hybrid").predict_action_chunk(repeated).view(2, 3, -1, 7)
    chunk = tiny_policy("hybrid", samples=3).predict_action_chunk(obs)
    assert torch.allclose(chunk, flows.median(dim=1).values, atol=1e-6)
    assert not torch.allclose(chunk, flows[:, 0], atol=1e-4)


def test_inference_options_replace_a_checkpoints_config_for_one_load(tmp_path):
    tiny_policy("hybrid").save_pretrained(tmp_path)
    assert load_policy(str(tmp_path), samples=3).config.samples == 3
    assert load_policy(str(tmp_path)).config.samples == 1  # the checkpoint itself is left alone
    with pytest.raises(UsageError, match="model.width does not apply to a hybrid checkpoint; allowed: model.samples"):
        load_policy(str(tmp_path), width=64)
    with pytest.raises(UsageError, match="model.samples 0; allowed: a whole number >= 1"):
        load_policy(str(tmp_path), samples=0)
    with pytest.raises(UsageError, match="do not apply to 'random'"):
        load_policy(RANDOM, samples=3)


def test_registry_names_and_errors(tmp_path, monkeypatch):
    from vlactl.models import registry

    assert load_policy(RANDOM).name == "hybrid"
    with pytest.raises(UsageError, match="allowed"):
        load_policy("no-such-model")
    monkeypatch.setattr(registry, "DEFAULT_RUN_DIR", str(tmp_path / "runs" / "{name}"))
    monkeypatch.setattr(registry, "SHIPPED_DIR", str(tmp_path / "shipped" / "{name}"))
    with pytest.raises(UsageError, match="train-policy"):
        load_policy("hybrid")


def test_model_name_prefers_own_training_run_over_shipped(tmp_path, monkeypatch):
    from vlactl.models import registry

    monkeypatch.setattr(registry, "DEFAULT_RUN_DIR", str(tmp_path / "runs" / "{name}"))
    monkeypatch.setattr(registry, "SHIPPED_DIR", str(tmp_path / "shipped" / "{name}"))
    for folder in (tmp_path / "shipped" / "hybrid", tmp_path / "runs" / "hybrid" / "checkpoint"):
        folder.mkdir(parents=True)
    tiny_policy("hybrid").save_pretrained(tmp_path / "shipped" / "hybrid")
    assert registry.resolve_checkpoint("hybrid") == tmp_path / "shipped" / "hybrid"
    tiny_policy("hybrid").save_pretrained(tmp_path / "runs" / "hybrid" / "checkpoint")
    assert registry.resolve_checkpoint("hybrid") == tmp_path / "runs" / "hybrid" / "checkpoint"


@pytest.mark.parametrize("name", list(MODELS))
def test_model_yaml_matches_config_class(name):
    yaml = OmegaConf.to_container(OmegaConf.load(CONF_DIR / "model" / f"{name}.yaml"))["model"]
    assert yaml.pop("name") == name
    config = policy_class(name).config_class
    assert yaml == {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(config()).items()}


@pytest.mark.parametrize("attention", ["causal", "bidirectional"])
def test_autoregressive_decoding_matches_teacher_forcing(attention):
    """Training and decoding see the same attention pattern: fed its own greedy chunk, the training forward
    predicts every token of it."""
    policy = tiny_policy("autoregressive", prompt_attention=attention, decode="argmax")
    inputs = policy.processor.observation(observation())
    with torch.no_grad():
        chunk = policy._sample(inputs)
        ids = torch.round((chunk + 1) / 2 * (policy.config.bins - 1)).long()
        batch = {**inputs, "actions": ids, "action_pad": torch.zeros(ids.shape[:2], dtype=torch.bool)}
        _, stats = policy.forward(batch)
    assert stats["token_accuracy"] == 1.0


def test_autoregressive_median_decode_takes_the_median_bin():
    """Mass 0.3 on bin 10, 0.25 on bin 20, 0.45 on bin 200: argmax picks 200, the median 20."""
    probs = torch.full((1, 256), 1e-9)
    probs[0, [10, 20, 200]] = torch.tensor([0.3, 0.25, 0.45])
    picks = {d: int(tiny_policy("autoregressive", decode=d)._pick(probs.log())) for d in ("argmax", "median")}
    assert picks == {"argmax": 200, "median": 20}
    with pytest.raises(UsageError, match="decode 'mean'; allowed: argmax, median"):
        tiny_policy("autoregressive", decode="mean")


def test_autoregressive_prompt_attention_is_checked():
    with pytest.raises(UsageError, match="prompt_attention 'sideways'; allowed: causal, bidirectional"):
        tiny_policy("autoregressive", prompt_attention="sideways")


def test_autoregressive_prompt_attention_decides_what_the_prompt_sees():
    """Under a prefix LM the first image token's output depends on the state token at the prompt's end."""
    unchanged = {}
    for attention in ("causal", "bidirectional"):
        policy = tiny_policy("autoregressive", prompt_attention=attention)
        first = []
        hook = policy.backbone.norm.register_forward_hook(lambda module, args, out: first.append(out[:, 0]))
        for shift in (0.0, 0.5):
            inputs = policy.processor.observation(observation())
            inputs["state"] = inputs["state"] + shift
            with torch.no_grad():
                policy._prefill(inputs)
        hook.remove()
        unchanged[attention] = torch.equal(*first)
    assert unchanged == {"causal": True, "bidirectional": False}
