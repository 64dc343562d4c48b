"""The real VLAs' adapters on tiny random checkpoints of their library classes (see real_model_fixtures.py): loading
through the registry, layer names, read-out sets, reading and writing a layer through the hooks, action
conventions, and the pipeline's own commands with `model.checkpoint=`."""

import numpy as np
import pytest
import torch
from real_model_fixtures import OPENVLA_PROMPT, pi05_tiny, write_llava, write_pi05, write_smolvla
from synthetic_demos import observation, write_synthetic_demos

from vlactl.config import load_policy_stage_config
from vlactl.errors import UsageError
from vlactl.models.base import PolicyInput
from vlactl.models.hooks import capture, intervene
from vlactl.models.openvla import bin_centres, decode_actions, to_libero_gripper
from vlactl.models.pi05 import openpi_transformers_installed
from vlactl.models.registry import load_policy
from vlactl.steering.activations import ActivationStore
from vlactl.steering.collect import run_collect

INSTRUCTIONS = ["pick up the black bowl on the stove", "place it on the plate"]


@pytest.fixture(scope="module")
def smolvla_checkpoint(tmp_path_factory):
    return write_smolvla(tmp_path_factory.mktemp("smolvla"))


@pytest.fixture(scope="module")
def openvla_checkpoint(tmp_path_factory):
    return write_llava(tmp_path_factory.mktemp("openvla"))


def load_smolvla(folder):
    return load_policy("smolvla", checkpoint=str(folder))


def load_openvla(folder):
    return load_policy("openvla", checkpoint=str(folder), prompt=OPENVLA_PROMPT, append_token=None)


def obs(batch=2):
    o = observation(batch)
    o.instruction = INSTRUCTIONS[:batch]
    return o


def seeded_chunk(vla, o, seed=1):
    torch.manual_seed(seed)  # the flow's initial noise
    return vla.predict_action_chunk(o)


def reading(vla, layer, o, fn=None):
    with intervene(vla, [layer], fn or (lambda name, h: None)), capture(vla, [layer]) as got:
        vla.encode(o)
    return got[layer][0]


# --- SmolVLA (LeRobot's own class) ----------------------------------------------------------------------------------
def test_smolvla_names_both_stacks_and_predicts_lerobot_chunks(smolvla_checkpoint):
    vla = load_smolvla(smolvla_checkpoint)
    assert vla.layer_names() == [f"backbone.{i}" for i in range(4)] + [f"expert.{i}" for i in range(4)]
    assert (vla.chunk_size, vla.replan_every) == (4, 2)
    assert vla.cameras == {"image": "observation.images.image", "wrist_image": "observation.images.image2"}
    chunk = seeded_chunk(vla, obs())
    assert chunk.shape == (2, 4, 7) and torch.isfinite(chunk).all()
    assert torch.equal(chunk, seeded_chunk(vla, obs()))


def rows_equal_alone(vla):
    """A server's batch (`predict_rows`): each row gets the chunk and the noise stream it would get predicted alone
    (to rounding: a bfloat16 forward rounds a batch of two otherwise than a batch of one)."""
    atol = 1e-5 if next(vla.policy.parameters()).dtype == torch.float32 else 5e-2
    o = obs()
    states = []
    for seed in (3, 4):
        torch.manual_seed(seed)
        states.append(vla.sampling_state())
    chunks, after = vla.predict_rows(o, states)
    for i, state in enumerate(states):
        vla.set_sampling_state(state)
        alone = vla.predict_action_chunk(observation_row(o, i))
        assert torch.allclose(chunks[i : i + 1], alone, atol=atol) and torch.equal(after[i], vla.sampling_state())
    assert not torch.allclose(chunks[0], chunks[1])


def observation_row(o, i):
    return PolicyInput({k: v[i : i + 1] for k, v in o.images.items()}, o.state[i : i + 1], o.instruction[i : i + 1])


def test_smolvla_batches_a_servers_rows_in_one_forward_as_each_alone(smolvla_checkpoint):
    rows_equal_alone(load_smolvla(smolvla_checkpoint))


def test_smolvla_read_out_sets_follow_the_prefix_it_builds(smolvla_checkpoint):
    vla = load_smolvla(smolvla_checkpoint)
    with capture(vla, vla.layer_names()) as got:
        vla.encode(obs())
    assert {name: tuple(got[name][0].shape) for name in ("backbone.0", "expert.0")} == {
        "backbone.0": (2, vla.layer_width("backbone.0")), "expert.0": (2, vla.layer_width("expert.0"))}
    image, text, prefix = (vla.token_mask("backbone.0", p) for p in ("image", "text", "prefix"))
    assert image.sum(1).tolist() == [8, 8]  # two cameras x 4 tokens (32 px, 8 px patches, pixel shuffle 2)
    tokenizer = vla.policy.model.vlm_with_expert.processor.tokenizer
    assert text.sum(1).tolist() == [len(tokenizer(t + "\n")["input_ids"]) for t in INSTRUCTIONS]
    assert (prefix.sum(1) == image.sum(1) + text.sum(1) + 1).all()  # + the state token
    assert not (image & text).any()


def check_writing(vla, layer, min_change, atol=1e-4):
    """Writing u at `layer` moves its pooled reading by exactly u (up to `atol`: the layer's dtype) and changes the
    actions; no hook outlives it."""
    u = torch.full((2, vla.layer_width(layer)), 0.5)
    before, after = reading(vla, layer, obs()), reading(vla, layer, obs(), lambda name, h: u)
    torch.testing.assert_close(after.float() - before.float(), u, atol=atol, rtol=0)
    plain = seeded_chunk(vla, obs())
    with intervene(vla, [layer], lambda name, h: 10 * u):
        steered = seeded_chunk(vla, obs())
    assert (steered - plain).abs().max() > min_change
    assert torch.equal(plain, seeded_chunk(vla, obs()))  # hooks are gone after the context


def check_last_backbone_layer_is_not_steerable(vla, last):
    """The expert reads each backbone layer's keys/values, made from that layer's input: writing the last backbone
    layer's output cannot move the actions, and the model does not offer it for steering."""
    plain = seeded_chunk(vla, obs())
    with intervene(vla, [last], lambda name, h: torch.full_like(h, 10.0)):
        assert torch.equal(seeded_chunk(vla, obs()), plain)
    assert last not in vla.steerable_layers() and len(vla.steerable_layers()) == len(vla.layer_names()) - 1


def collect(model, checkpoint, tmp_path, layers):
    """`vlactl collect model=<model> model.checkpoint=...` on 2 synthetic episodes (4 and 5 frames)."""
    demos = write_synthetic_demos(tmp_path / "demos", episodes=2, frames=4)
    cfg = load_policy_stage_config("collect", [
        f"model={model}", f"model.checkpoint={checkpoint}", f"dataset={demos}", f"output_dir={tmp_path / 'a'}",
        f"cache_dir={tmp_path / 'cache'}", "batch_size=4", "threads=1", f"layers=[{','.join(layers)}]",
    ])
    store = ActivationStore(run_collect(cfg))
    assert store.layers == layers and store.n_frames == 4 + 5
    assert all(torch.isfinite(store.load([layer])).all() for layer in layers)  # one at a time: widths differ


@pytest.mark.parametrize("layer", ["backbone.1", "expert.2"])
def test_smolvla_writing_a_layer_moves_its_reading_by_u_and_changes_the_actions(smolvla_checkpoint, layer):
    check_writing(load_smolvla(smolvla_checkpoint), layer, min_change=1e-3)


def test_smolvla_last_backbone_layer_is_not_steerable(smolvla_checkpoint):
    check_last_backbone_layer_is_not_steerable(load_smolvla(smolvla_checkpoint), "backbone.3")


def test_smolvla_collect_runs_through_the_pipeline_command(smolvla_checkpoint, tmp_path):
    collect("smolvla", smolvla_checkpoint, tmp_path, ["backbone.3", "expert.0"])


# --- π0.5 (LeRobot's own class on openpi's transformers branch, tiny: see pi05_tiny) --------------------------------
NO_OPENPI = ("π0.5 runs on openpi's transformers branch (transformers-openpi), not this transformers: `make test-real` "
             "runs these tests with it laid over .venv")


@pytest.fixture(scope="module", params=["float32", "bfloat16"])
def pi05_checkpoint(request, tmp_path_factory):
    if not openpi_transformers_installed():
        pytest.skip(NO_OPENPI)
    return write_pi05(tmp_path_factory.mktemp(f"pi05_{request.param}"), dtype=request.param)


@pytest.fixture
def pi05(pi05_checkpoint):
    with pi05_tiny(pi05_checkpoint):  # LeRobot's sizes shrunk for this test only
        yield load_policy("pi05", checkpoint=str(pi05_checkpoint))


def test_pi05_loads_its_weights_names_both_stacks_and_predicts_lerobot_chunks(pi05, pi05_checkpoint):
    assert pi05.layer_names() == ["backbone.0", "backbone.1", "expert.0", "expert.1"]
    assert (pi05.chunk_size, pi05.replan_every) == (4, 2)
    assert pi05.cameras == {"image": "observation.images.image", "wrist_image": "observation.images.image2"}
    again = load_policy("pi05", checkpoint=str(pi05_checkpoint)).policy.state_dict()
    # LeRobot prints a missing tied key and carries on; a fresh random init would differ, so the file was read
    assert all(torch.equal(value, again[key]) for key, value in pi05.policy.state_dict().items())
    chunk = seeded_chunk(pi05, obs())
    assert chunk.shape == (2, 4, 7) and chunk.dtype == torch.float32 and torch.isfinite(chunk).all()
    assert torch.equal(chunk, seeded_chunk(pi05, obs()))


def test_pi05_batches_a_servers_rows_in_one_forward_as_each_alone(pi05):
    rows_equal_alone(pi05)


def test_pi05_runs_the_branch_gemma_in_the_checkpoint_dtype(pi05):
    """The branch's decoder layers return tuples (the hooks read and write their first item), the expert's norms are
    adaptive, and a bfloat16 checkpoint keeps LeRobot's split: layers in bfloat16, norms in float32."""
    dtype = getattr(torch, pi05.policy.config.dtype)
    layer = pi05.layer_module("expert.0")
    outputs = []
    handle = layer.register_forward_hook(lambda module, args, output: outputs.append(output))
    try:
        pi05.encode(obs())
    finally:
        handle.remove()
    assert isinstance(outputs[0], tuple) and outputs[0][0].dtype == dtype
    assert layer.input_layernorm.dense is not None and layer.input_layernorm.dense.weight.dtype == torch.float32
    assert pi05.layer_module("backbone.0").input_layernorm.cond_dim is None
    assert layer.mlp.up_proj.weight.dtype == dtype
    with capture(pi05, pi05.layer_names()) as got:
        pi05.encode(obs())
    assert {got[name][0].dtype for name in pi05.layer_names()} == {dtype}


def test_pi05_read_out_sets_follow_the_prefix_it_builds(pi05):
    from lerobot.processor.tokenizer_processor import TokenizerProcessorStep

    with capture(pi05, pi05.layer_names()) as got:
        pi05.encode(obs())
    assert {name: tuple(got[name][0].shape) for name in ("backbone.0", "expert.0")} == {
        "backbone.0": (2, 32), "expert.0": (2, 16)}
    image, text, prefix = (pi05.token_mask("backbone.0", p) for p in ("image", "text", "prefix"))
    assert image.sum(1).tolist() == [32, 32] and image[:, :32].all()  # two cameras x (32 px / 8 px)^2 patches, first
    # the text is the pipeline's whole prompt ("Task: ..., State: <bins>;\nAction: "), tokenised by the tokenizer
    # LeRobot loads by its hub id: π0.5 has no state token
    batch = pi05._batch(obs())
    assert torch.equal(text.sum(1), batch["observation.language.attention_mask"].sum(1))
    tokenizer = next(s for s in pi05.preprocessor.steps if isinstance(s, TokenizerProcessorStep)).input_tokenizer
    prompt = tokenizer.convert_ids_to_tokens(batch["observation.language.tokens"][0, :int(text[0].sum())].tolist())
    assert prompt[:3] == ["<bos>", "Task:", "pick"] and prompt[-1] == "Action:" and "State:" in prompt
    assert text[:, 32].all() and not (image & text).any() and torch.equal(prefix, image | text)
    assert pi05.token_mask("expert.1", "prefix").sum(1).tolist() == [4, 4]  # the chunk's action tokens


@pytest.mark.parametrize("layer", ["backbone.0", "expert.1"])
def test_pi05_writing_a_layer_moves_its_reading_by_u_and_changes_the_actions(pi05, layer):
    # Random adaptive-norm gates are small, so the expert barely reads the prefix: writing backbone.0 moves the
    # actions by little, yet far above float noise (a plain re-run is bit-identical). backbone.1, the last, could not
    # move them at all: the expert attends to each layer's keys/values, made from that layer's input. bfloat16 keeps
    # 8 significant bits: the written stream is rounded to ~0.4% of its values.
    check_writing(pi05, layer, min_change=1e-5, atol=1e-4 if pi05.policy.config.dtype == "float32" else 1e-2)


def test_pi05_last_backbone_layer_is_not_steerable(pi05):
    check_last_backbone_layer_is_not_steerable(pi05, "backbone.1")


def test_pi05_collect_runs_through_the_pipeline_command(pi05_checkpoint, tmp_path):
    with pi05_tiny(pi05_checkpoint):
        collect("pi05", pi05_checkpoint, tmp_path, ["backbone.1", "expert.0"])


@pytest.mark.skipif(openpi_transformers_installed(), reason="openpi's transformers branch is installed")
def test_pi05_refuses_stock_transformers(tmp_path):
    with pytest.raises(UsageError, match="openpi's transformers branch.*transformers-openpi==4.53.3"):
        load_policy("pi05", checkpoint=str(tmp_path))


# --- OpenVLA (tiny LLaVA stand-in) ----------------------------------------------------------------------------------
def test_openvla_decodes_action_tokens_like_predict_action():
    vocab, centres = 1000, bin_centres()
    tokens = np.array([[vocab - 1 - 0, vocab - 1 - 254, vocab - 1 - 127, vocab - 1, vocab - 1, vocab - 1, vocab - 1]])
    stats = {"q01": [-2.0] * 7, "q99": [2.0] * 7, "mask": [True] * 6 + [False]}
    actions = decode_actions(tokens, vocab, stats)
    np.testing.assert_allclose(actions[0, :3], 0.5 * (centres[[0, 254, 127]] + 1) * 4 - 2)
    assert actions[0, 6] == centres[0]  # the gripper is not un-normalised
    np.testing.assert_array_equal(to_libero_gripper(np.array([[0, 0, 0, 0, 0, 0, 0.9], [0] * 6 + [0.1]]))[:, 6],
                                  [-1.0, 1.0])  # open -> -1, close -> +1


def test_openvla_reads_the_prompt_pass_and_leaves_decode_steps_alone(openvla_checkpoint):
    vla = load_openvla(openvla_checkpoint)
    assert vla.layer_names() == ["backbone.0", "backbone.1", "backbone.2"] and vla.chunk_size == 1
    with capture(vla, vla.layer_names()) as got:
        chunk = vla.predict_action_chunk(obs())
    assert chunk.shape == (2, 1, 7) and set(chunk[:, 0, 6].tolist()) <= {-1.0, 1.0}
    assert [len(got[name]) for name in vla.layer_names()] == [2, 2, 2]  # one prompt pass per observation, no decodes
    dimensions = []
    with capture(vla, ["backbone.0"], "action") as written, \
            intervene(vla, ["backbone.0"], lambda name, h: dimensions.append(vla.written_dimension()), "action"):
        vla.encode_for(obs(), "action")
    assert len(written["backbone.0"]) == 2 * 7  # per observation: the prompt's last token, then 6 decode steps
    assert dimensions == list(range(7)) * 2
    vla.encode(obs())
    image, text, prefix = (vla.token_mask("backbone.0", p) for p in ("image", "text", "prefix"))
    assert image.sum(1).tolist() == [16, 16]  # (32 px / 8 px)^2 patches
    assert image[:, 0].logical_not().all() and image[:, 1:17].all()  # right after BOS
    assert (text.sum(1) + image.sum(1) == prefix.sum(1)).all() and prefix.sum(1)[0] != prefix.sum(1)[1]


def test_openvla_writing_a_layer_moves_its_reading_by_u_and_changes_the_actions(openvla_checkpoint):
    vla = load_openvla(openvla_checkpoint)
    u = torch.full((2, 32), 0.5)
    before, after = reading(vla, "backbone.1", obs()), reading(vla, "backbone.1", obs(), lambda name, h: u)
    torch.testing.assert_close(after - before, u, atol=1e-4, rtol=0)
    plain = vla.predict_action_chunk(obs())
    with intervene(vla, ["backbone.0"], lambda name, h: torch.full((h.shape[0], 32), 50.0)):
        steered = vla.predict_action_chunk(obs())
    assert not torch.equal(plain, steered)


def test_openvla_refuses_an_unknown_unnorm_key(openvla_checkpoint):
    with pytest.raises(UsageError, match="unnorm_key='bridge_orig'.*libero_spatial"):
        load_policy("openvla", checkpoint=str(openvla_checkpoint), unnorm_key="bridge_orig")


# --- options -----------------------------------------------------------------------------------------------------
def test_model_options_reach_the_adapter_and_are_refused_elsewhere():
    cfg = load_policy_stage_config("collect", ["model=openvla", "model.checkpoint=/ckpt", "model.unnorm_key=libero_10"])
    assert cfg.model == "openvla" and dict(cfg.model_args) == {"checkpoint": "/ckpt", "unnorm_key": "libero_10"}
    with pytest.raises(UsageError, match="model=pi05 needs model.checkpoint"):
        load_policy("pi05")
    with pytest.raises(UsageError, match="model.checkpoint does not apply to a hybrid checkpoint; allowed: model.samples"):
        load_policy("hybrid", checkpoint="/ckpt")
