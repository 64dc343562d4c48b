"""Tiny random checkpoints of the real VLAs' library classes, written as a user's checkpoint folder would be.

- SmolVLA: LeRobot's own `SmolVLAPolicy` over a tiny local SmolVLM (config, word-level tokenizer trained here,
  processor) with LeRobot's pre/post-processor pipelines saved beside it - the real load and forward code.
- OpenVLA stand-in: OpenVLA's modeling code lives on the hub, so a tiny Hugging Face LLaVA (SigLIP patches projected
  into a Llama decoder, the same [BOS, patches, prompt] layout once the prompt starts with `<image>`) with OpenVLA's
  `norm_stats` in its config.
- π0.5: LeRobot's own `PI05Policy`, tiny, saved with its pipelines; it builds and runs only inside `pi05_standin`,
  which supplies what LeRobot's transformers branch changes (see there).
"""

from __future__ import annotations

import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import torch

WORDS = (
    "in: what action should the robot take to pick up black bowl between plate and ramekin place it on stove next "
    "cookie box wooden cabinet top drawer of table center ? out:"
).split()
STATE_DIM, ACTION_DIM = 8, 7
OPENVLA_PROMPT = "<image>In: What action should the robot take to {instruction}?\nOut:"


def _tokenizer(special: list[str], extra_tokens: list[str] = (), bos: str | None = None, **kwargs):
    from tokenizers import Tokenizer, models, pre_tokenizers, processors
    from transformers import PreTrainedTokenizerFast

    vocab = {token: i for i, token in enumerate([*special, *sorted(set(WORDS)), "\n", *extra_tokens])}
    tokenizer = Tokenizer(models.WordLevel(vocab, unk_token="<unk>"))
    tokenizer.pre_tokenizer = pre_tokenizers.WhitespaceSplit()
    if bos:
        tokenizer.post_processor = processors.TemplateProcessing(single=f"{bos} $A", special_tokens=[(bos, vocab[bos])])
    return PreTrainedTokenizerFast(tokenizer_object=tokenizer, unk_token="<unk>", pad_token="<pad>", **kwargs), vocab


TINY_TEXT = dict(hidden_size=32, intermediate_size=64, num_hidden_layers=4, num_attention_heads=4, num_key_value_heads=2,
                 head_dim=8)
TINY_VISION = dict(hidden_size=16, intermediate_size=32, num_hidden_layers=1, num_attention_heads=2, image_size=32,
                   patch_size=8)


def write_smolvlm(folder: Path, text: dict = TINY_TEXT, vision: dict = TINY_VISION, scale_factor: int = 2) -> Path:
    """A SmolVLM config, tokenizer and processor; `text`/`vision` set the widths (tiny by default)."""
    from transformers import SmolVLMConfig, SmolVLMImageProcessor, SmolVLMProcessor, SmolVLMVideoProcessor

    special = ["<unk>", "<pad>", "<|im_start|>", "<end_of_utterance>", "<fake_token_around_image>", "<global-img>",
               "<image>"]
    tokenizer, vocab = _tokenizer(
        special, bos_token="<|im_start|>", eos_token="<end_of_utterance>",
        extra_special_tokens={"fake_image_token": "<fake_token_around_image>", "global_image_token": "<global-img>",
                              "image_token": "<image>", "end_of_utterance_token": "<end_of_utterance>"},
    )
    SmolVLMConfig(
        text_config=dict(model_type="llama", vocab_size=len(vocab), max_position_embeddings=2048, **text),
        vision_config=vision, scale_factor=scale_factor, image_token_id=vocab["<image>"],
    ).save_pretrained(folder)
    size = {"longest_edge": vision["image_size"]}
    image_processor = SmolVLMImageProcessor(do_resize=False, do_image_splitting=False, size=size, max_image_size=size)
    tokens = (vision["image_size"] // vision["patch_size"] // scale_factor) ** 2
    SmolVLMProcessor(image_processor=image_processor, tokenizer=tokenizer, video_processor=SmolVLMVideoProcessor(),
                     image_seq_len=tokens).save_pretrained(folder)
    return folder


def write_smolvla(folder: Path, seed: int = 0, text: dict = TINY_TEXT, vision: dict = TINY_VISION,
                  scale_factor: int = 2, chunk_size: int = 4, steps: int = 2, device: str = "cpu") -> Path:
    """A SmolVLA checkpoint folder: policy weights + config + LeRobot's processor pipelines (identity stats)."""
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.smolvla.configuration_smolvla import SmolVLAConfig
    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy
    from lerobot.policies.smolvla.processor_smolvla import make_smolvla_pre_post_processors

    folder.mkdir(parents=True, exist_ok=True)
    vlm = write_smolvlm(folder / "smolvlm", text, vision, scale_factor)
    size = vision["image_size"]
    image = PolicyFeature(FeatureType.VISUAL, (3, size, size))
    config = SmolVLAConfig(
        vlm_model_name=str(vlm), load_vlm_weights=False, chunk_size=chunk_size, n_action_steps=chunk_size // 2,
        num_steps=steps, resize_imgs_with_padding=(size, size), num_vlm_layers=text["num_hidden_layers"],
        max_state_dim=STATE_DIM, max_action_dim=ACTION_DIM, tokenizer_max_length=16, device=device,
        input_features={"observation.images.image": image, "observation.images.image2": image,
                        "observation.state": PolicyFeature(FeatureType.STATE, (STATE_DIM,))},
        output_features={"action": PolicyFeature(FeatureType.ACTION, (ACTION_DIM,))},
    )
    torch.manual_seed(seed)
    policy = SmolVLAPolicy(config)
    stats = {"observation.state": {"mean": torch.zeros(STATE_DIM), "std": torch.ones(STATE_DIM)},
             "action": {"mean": torch.zeros(ACTION_DIM), "std": torch.ones(ACTION_DIM)}}
    for part in (policy, *make_smolvla_pre_post_processors(config, stats)):
        part.save_pretrained(folder)
    return folder


def write_llava(folder: Path, seed: int = 0, text: dict = None, vision: dict = TINY_VISION) -> Path:
    """A LLaVA with OpenVLA's action tokens (the last 256 ids) and `norm_stats` for `libero_spatial`; tiny unless
    `text` (Llama widths) and `vision` (SigLIP widths) say otherwise."""
    from transformers import LlavaConfig, LlavaForConditionalGeneration, LlavaProcessor, SiglipImageProcessor

    tokenizer, vocab = _tokenizer(["<unk>", "<pad>", "<s>", "</s>", "<image>"],
                                  [f"<action_{i}>" for i in range(256)], bos="<s>", bos_token="<s>", eos_token="</s>")
    tokenizer.add_special_tokens({"additional_special_tokens": ["<image>"]})
    config = LlavaConfig(
        text_config=dict(model_type="llama", vocab_size=len(vocab), max_position_embeddings=1024,
                         pad_token_id=vocab["<pad>"], **(text or dict(TINY_TEXT, num_hidden_layers=3))),
        vision_config=dict(model_type="siglip_vision_model", **vision),
        image_token_index=vocab["<image>"], vision_feature_select_strategy="full", vision_feature_layer=-1,
    )
    config.norm_stats = {"libero_spatial": {"action": {"q01": [-0.5] * 6 + [0.0], "q99": [0.5] * 6 + [1.0],
                                                       "mask": [True] * 6 + [False]}}}
    torch.manual_seed(seed)
    LlavaForConditionalGeneration(config).save_pretrained(folder)
    size = {"height": vision["image_size"], "width": vision["image_size"]}
    LlavaProcessor(image_processor=SiglipImageProcessor(size=size), tokenizer=tokenizer,
                   patch_size=vision["patch_size"], vision_feature_select_strategy="full",
                   num_additional_image_tokens=0).save_pretrained(folder)
    return folder


# --- π0.5: LeRobot's own PI05Policy on stock transformers ---------------------------------------------------------
# LeRobot 0.4.4 builds π0.5 only on its transformers branch (`fix/lerobot_openpi`, openpi's `transformers_replace`),
# from full-size Gemma variants. `pi05_standin` supplies, while it is active, what that branch changes for inference
# and shrinks the sizes LeRobot hard-wires; everything else is LeRobot's and transformers' own code.
PALIGEMMA_TOKENIZER = "google/paligemma-3b-pt-224"  # the hub id LeRobot's π0.5 pipeline saves and loads
PI05_TOKENIZER_DIR = "paligemma"  # where write_pi05 puts the tiny stand-in for it, inside the checkpoint folder
# The two variant names LeRobot accepts -> tiny widths. Heads as the real ones (8 query, 1 key/value, shared by both
# stacks: the expert attends to the backbone's keys/values, and LeRobot's joint training pass hard-codes 8 heads).
PI05_GEMMA = {"gemma_2b": dict(width=32, depth=2, mlp_dim=64, num_heads=8, num_kv_heads=1, head_dim=4),
              "gemma_300m": dict(width=16, depth=2, mlp_dim=32, num_heads=8, num_kv_heads=1, head_dim=4)}


class AdaRMSNorm(torch.nn.Module):
    """The branch's GemmaRMSNorm: `forward(x, cond)` returns (normed, gate). Given `cond_dim` it is adaptive: scale,
    shift and a residual gate come from a dense layer on `cond` (π0.5's time embedding) instead of a weight."""

    def __init__(self, dim: int, eps: float = 1e-6, cond_dim: int | None = None):
        super().__init__()
        self.eps, self.cond_dim = eps, cond_dim
        self.dense = None if cond_dim is None else torch.nn.Linear(cond_dim, 3 * dim)
        if cond_dim is None:
            self.weight = torch.nn.Parameter(torch.zeros(dim))

    def forward(self, x, cond=None):
        normed = x.float() * torch.rsqrt(x.float().pow(2).mean(-1, keepdim=True) + self.eps)
        if cond is None or self.dense is None:
            return (normed * (1.0 + self.weight.float())).to(x.dtype), None
        modulation = self.dense(cond)
        scale, shift, gate = (modulation[:, None] if x.dim() == 3 else modulation).chunk(3, dim=-1)
        return (normed * (1 + scale.float()) + shift.float()).to(x.dtype), gate.to(x.dtype)


def _gated_residual(x, y, gate):
    return x + y if gate is None else x + y * gate


class _PrefixCache:
    """The prefix's keys/values seen through `update` without growing: the branch's attention concatenates the cache
    when `use_cache=False`, so each denoising step attends to the prefix and its own action tokens only."""

    def __init__(self, cache):
        self.cache = cache

    def update(self, keys, values, layer_idx, cache_kwargs=None):
        cached_keys, cached_values = self.cache[layer_idx]
        return torch.cat([cached_keys, keys], dim=-2), torch.cat([cached_values, values], dim=-2)


def _decoder_layer_forward(self, hidden_states, attention_mask=None, position_ids=None, past_key_values=None,
                           use_cache=False, cache_position=None, position_embeddings=None, adarms_cond=None, **kwargs):
    normed, gate = self.input_layernorm(hidden_states, adarms_cond)
    attended, _ = self.self_attn(hidden_states=normed, attention_mask=attention_mask, position_ids=position_ids,
                                 past_key_values=past_key_values, use_cache=use_cache, cache_position=cache_position,
                                 position_embeddings=position_embeddings, **kwargs)
    hidden_states = _gated_residual(hidden_states, attended, gate)
    normed, gate = self.post_attention_layernorm(hidden_states, adarms_cond)
    return _gated_residual(hidden_states, self.mlp(normed), gate)


def _gemma_model_forward(self, input_ids=None, attention_mask=None, position_ids=None, past_key_values=None,
                         inputs_embeds=None, use_cache=None, cache_position=None, adarms_cond=None, **kwargs):
    """Stock GemmaModel.forward as the branch changes it: no sqrt(width) scaling of the inputs (π0.5 scales its own
    text embeddings), `adarms_cond` to every norm, and the prefix cache read but not grown when use_cache=False."""
    from transformers.cache_utils import DynamicCache
    from transformers.masking_utils import create_causal_mask
    from transformers.modeling_outputs import BaseModelOutputWithPast

    hidden = self.embed_tokens(input_ids) if inputs_embeds is None else inputs_embeds
    if use_cache and past_key_values is None:
        past_key_values = DynamicCache(config=self.config)
    if cache_position is None:
        seen = past_key_values.get_seq_length() if past_key_values is not None else 0
        cache_position = torch.arange(seen, seen + hidden.shape[1], device=hidden.device)
    if position_ids is None:
        position_ids = cache_position.unsqueeze(0)
    mask = create_causal_mask(config=self.config, input_embeds=hidden, attention_mask=attention_mask,
                              cache_position=cache_position, past_key_values=past_key_values, position_ids=position_ids)
    layer_cache = past_key_values if use_cache or past_key_values is None else _PrefixCache(past_key_values)
    position_embeddings = self.rotary_emb(hidden, position_ids)
    for layer in self.layers[: self.config.num_hidden_layers]:
        hidden = layer(hidden, attention_mask=mask, position_ids=position_ids, past_key_values=layer_cache,
                       use_cache=use_cache, cache_position=cache_position, position_embeddings=position_embeddings,
                       adarms_cond=adarms_cond, **kwargs)
    hidden, _ = self.norm(hidden, adarms_cond)
    return BaseModelOutputWithPast(last_hidden_state=hidden, past_key_values=past_key_values if use_cache else None)


@contextmanager
def pi05_standin(checkpoint: Path) -> Iterator[None]:
    """While active, LeRobot 0.4.4's PI05Policy builds, loads and runs on stock transformers 4.57, tiny:

    - the branch's Gemma: adaptive RMSNorm (`use_adarms` configs: the action expert), gated residuals, `adarms_cond`
      through GemmaModel.forward, no input scaling, the prefix cache left ungrown across denoising steps; its
      PaliGemma's image features without stock's 1/sqrt(width); and `transformers.models.siglip.check`, the module
      LeRobot imports to ask whether the branch is installed;
    - sizes: `get_gemma_config` -> PI05_GEMMA, PaliGemma's SigLIP -> TINY_VISION and its projector onto the text width
      (projection_dim, hard-wired to 2048 = gemma_2b's width), the PaliGemma tokenizer -> the one in
      `checkpoint/paligemma` (SigLIP's MLP keeps LeRobot's 4304 and the vocabularies their 257152 rows: cheap).
    """
    from types import ModuleType, SimpleNamespace

    import pytest
    from lerobot.policies.pi05 import modeling_pi05
    from lerobot.processor import tokenizer_processor
    from transformers import AutoTokenizer, PaliGemmaConfig
    from transformers.models.auto import CONFIG_MAPPING
    from transformers.models.gemma import modeling_gemma as gemma
    from transformers.models.paligemma import modeling_paligemma

    stock_model_init, stock_init_weights = gemma.GemmaModel.__init__, gemma.GemmaPreTrainedModel._init_weights

    def model_init(self, config):
        cond_dim = config.adarms_cond_dim if getattr(config, "use_adarms", False) else None
        with pytest.MonkeyPatch.context() as inner:  # every norm GemmaModel builds (its layers' too) gets cond_dim
            inner.setattr(gemma, "GemmaRMSNorm", lambda dim, eps: AdaRMSNorm(dim, eps, cond_dim))
            stock_model_init(self, config)

    def init_weights(self, module):
        if not (isinstance(module, AdaRMSNorm) and module.dense is not None):  # no weight to zero; dense: a Linear
            stock_init_weights(self, module)

    def projector_init(self, config):
        torch.nn.Module.__init__(self)
        self.linear = torch.nn.Linear(config.vision_config.hidden_size, config.text_config.hidden_size)

    check = ModuleType("transformers.models.siglip.check")
    check.check_whether_transformers_replace_is_installed_correctly = lambda: True
    tokenizer = str(checkpoint / PI05_TOKENIZER_DIR)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(gemma.GemmaModel, "__init__", model_init)
        mp.setattr(gemma.GemmaModel, "forward", _gemma_model_forward)
        mp.setattr(gemma.GemmaDecoderLayer, "forward", _decoder_layer_forward)
        mp.setattr(gemma.GemmaPreTrainedModel, "_init_weights", init_weights)
        mp.setattr(gemma, "_gated_residual", _gated_residual, raising=False)  # LeRobot's training path calls it
        mp.setattr(modeling_paligemma.PaliGemmaModel, "get_image_features",
                   lambda self, pixels: self.multi_modal_projector(self.vision_tower(pixels).last_hidden_state))
        mp.setattr(modeling_paligemma.PaliGemmaMultiModalProjector, "__init__", projector_init)
        mp.setitem(sys.modules, check.__name__, check)
        mp.setattr(modeling_pi05, "get_gemma_config", lambda variant: modeling_pi05.GemmaConfig(**PI05_GEMMA[variant]))
        mp.setattr(modeling_pi05, "CONFIG_MAPPING", {
            "paligemma": lambda: PaliGemmaConfig(vision_config=dict(model_type="siglip_vision_model", **TINY_VISION)),
            "gemma": CONFIG_MAPPING["gemma"]})
        mp.setattr(tokenizer_processor, "AutoTokenizer", SimpleNamespace(
            from_pretrained=lambda name, **kw: AutoTokenizer.from_pretrained(
                tokenizer if name == PALIGEMMA_TOKENIZER else name, **kw)))
        yield


def write_pi05(folder: Path, seed: int = 0, chunk_size: int = 4, steps: int = 2) -> Path:
    """A π0.5 checkpoint folder as LeRobot writes one: policy weights + config + processor pipelines (identity quantile
    stats), plus the tiny PaliGemma tokenizer that `pi05_standin(folder)` serves for PALIGEMMA_TOKENIZER."""
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.pi05.configuration_pi05 import PI05Config
    from lerobot.policies.pi05.modeling_pi05 import PI05Policy
    from lerobot.policies.pi05.processor_pi05 import make_pi05_pre_post_processors

    folder.mkdir(parents=True, exist_ok=True)
    # π0.5's prompt: "Task: <instruction>, State: <32 state bins 0..255>;\nAction: " after PaliGemma's BOS
    words = ["Task:", "State:", "Action:", *map(str, range(256))]
    tokenizer, _ = _tokenizer(["<unk>", "<pad>", "<bos>", "<eos>"], words, bos="<bos>", bos_token="<bos>",
                              eos_token="<eos>")
    tokenizer.save_pretrained(folder / PI05_TOKENIZER_DIR)
    size = TINY_VISION["image_size"]
    image = PolicyFeature(FeatureType.VISUAL, (3, size, size))
    config = PI05Config(
        chunk_size=chunk_size, n_action_steps=chunk_size // 2, num_inference_steps=steps, image_resolution=(size, size),
        tokenizer_max_length=48, device="cpu",  # state and actions padded to 32 dims, as LeRobot's π0.5 checkpoints
        input_features={"observation.images.image": image, "observation.images.image2": image,
                        "observation.state": PolicyFeature(FeatureType.STATE, (STATE_DIM,))},
        output_features={"action": PolicyFeature(FeatureType.ACTION, (ACTION_DIM,))},
    )
    stats = {key: {"q01": -torch.ones(dim), "q99": torch.ones(dim)}
             for key, dim in (("observation.state", STATE_DIM), ("action", ACTION_DIM))}
    with pi05_standin(folder):
        torch.manual_seed(seed)
        policy = PI05Policy(config)
        for part in (policy, *make_pi05_pre_post_processors(config, stats)):
            part.save_pretrained(folder)
    return folder
