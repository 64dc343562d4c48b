"""Tiny random checkpoints of the real VLAs' library classes, written as a user's checkpoint folder would be.

- SmolVLA: LeRobot's own `SmolVLAPolicy` over a tiny local SmolVLM (config, word-level tokenizer trained here,
  processor) with LeRobot's pre/post-processor pipelines saved beside it - the real load and forward code.
- OpenVLA stand-in: OpenVLA's modeling code lives on the hub, so a tiny Hugging Face LLaVA (SigLIP patches projected
  into a Llama decoder, the same [BOS, patches, prompt] layout once the prompt starts with `<image>`) with OpenVLA's
  `norm_stats` in its config.
- π0.5: LeRobot's own `PI05Policy` on openpi's transformers branch (transformers-openpi, laid over .venv), tiny and
  saved with its pipelines; it builds and runs inside `pi05_tiny`, which shrinks the sizes LeRobot hard-wires.
"""

from __future__ import annotations

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


# --- π0.5: LeRobot's own PI05Policy on openpi's transformers branch (`make test-real`) ------------------------
# LeRobot 0.4.4 builds π0.5 from full-size Gemma variants (a full-size π0.5 takes minutes to construct on 2 cores);
# `pi05_tiny` shrinks what it hard-wires. Everything else is LeRobot's and the branch's own code.
PALIGEMMA_TOKENIZER = "google/paligemma-3b-pt-224"  # the hub id LeRobot's π0.5 pipeline saves and loads
PI05_HUB_CACHE = "hub"  # where write_pi05 puts a hub cache holding a tiny tokenizer under that id
# The two variant names LeRobot accepts -> tiny widths. Heads as the real ones (8 query, 1 key/value, shared by both
# stacks: the expert attends to the backbone's keys/values, and LeRobot's joint training pass hard-codes 8 heads).
PI05_GEMMA = {"gemma_2b": dict(width=32, depth=2, mlp_dim=64, num_heads=8, num_kv_heads=1, head_dim=4),
              "gemma_300m": dict(width=16, depth=2, mlp_dim=32, num_heads=8, num_kv_heads=1, head_dim=4)}


@contextmanager
def pi05_tiny(checkpoint: Path) -> Iterator[None]:
    """While active, LeRobot 0.4.4's PI05Policy is built tiny and its pipeline finds PALIGEMMA_TOKENIZER offline:

    - `get_gemma_config` -> PI05_GEMMA; PaliGemma's SigLIP -> TINY_VISION and its projector onto the text width
      (LeRobot hard-wires projection_dim 2048, gemma_2b's width); SigLIP's MLP keeps LeRobot's 4304 and the
      vocabularies their 257152 rows (cheap);
    - transformers' default hub cache -> `checkpoint/hub`, so LeRobot's own `AutoTokenizer.from_pretrained(hub id)`
      resolves the id from a hub cache as on an offline machine that has the real one.
    """
    import pytest
    from lerobot.policies.pi05 import modeling_pi05
    from transformers import PaliGemmaConfig
    from transformers.models.auto import CONFIG_MAPPING
    from transformers.models.paligemma import modeling_paligemma
    from transformers.utils import hub

    def projector_init(self, config):
        torch.nn.Module.__init__(self)
        self.linear = torch.nn.Linear(config.vision_config.hidden_size, config.text_config.hidden_size)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(modeling_pi05, "get_gemma_config", lambda variant: modeling_pi05.GemmaConfig(**PI05_GEMMA[variant]))
        mp.setattr(modeling_pi05, "CONFIG_MAPPING", {
            "paligemma": lambda: PaliGemmaConfig(vision_config=dict(model_type="siglip_vision_model", **TINY_VISION)),
            "gemma": CONFIG_MAPPING["gemma"]})
        mp.setattr(modeling_paligemma.PaliGemmaMultiModalProjector, "__init__", projector_init)
        mp.setattr(hub, "TRANSFORMERS_CACHE", str(checkpoint / PI05_HUB_CACHE))
        yield


def write_hub_cache(cache: Path, repo_id: str, save) -> None:
    """Lay out `save(folder)`'s files as the hub cache holds a downloaded model repo (one snapshot, `main`)."""
    repo, commit = cache / f"models--{repo_id.replace('/', '--')}", "0" * 40
    save(repo / "snapshots" / commit)
    (repo / "refs").mkdir(parents=True)
    (repo / "refs" / "main").write_text(commit)


def write_pi05(folder: Path, seed: int = 0, chunk_size: int = 4, steps: int = 2, dtype: str = "float32") -> Path:
    """A π0.5 checkpoint folder as LeRobot writes one: policy weights (in `dtype`) + config + processor pipelines
    (identity quantile stats), plus the hub cache with the tiny PaliGemma tokenizer that `pi05_tiny(folder)` uses."""
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.pi05.configuration_pi05 import PI05Config
    from lerobot.policies.pi05.modeling_pi05 import PI05Policy
    from lerobot.policies.pi05.processor_pi05 import make_pi05_pre_post_processors

    folder.mkdir(parents=True, exist_ok=True)
    # π0.5's prompt: "Task: <instruction>, State: <32 state bins 0..255>;\nAction: " after PaliGemma's BOS
    words = ["Task:", "State:", "Action:", *map(str, range(256))]
    tokenizer, _ = _tokenizer(["<unk>", "<pad>", "<bos>", "<eos>"], words, bos="<bos>", bos_token="<bos>",
                              eos_token="<eos>")
    write_hub_cache(folder / PI05_HUB_CACHE, PALIGEMMA_TOKENIZER, tokenizer.save_pretrained)
    size = TINY_VISION["image_size"]
    image = PolicyFeature(FeatureType.VISUAL, (3, size, size))
    config = PI05Config(
        chunk_size=chunk_size, n_action_steps=chunk_size // 2, num_inference_steps=steps, image_resolution=(size, size),
        tokenizer_max_length=48, device="cpu", dtype=dtype,  # state/actions padded to 32 dims, as LeRobot's π0.5
        input_features={"observation.images.image": image, "observation.images.image2": image,
                        "observation.state": PolicyFeature(FeatureType.STATE, (STATE_DIM,))},
        output_features={"action": PolicyFeature(FeatureType.ACTION, (ACTION_DIM,))},
    )
    stats = {key: {"q01": -torch.ones(dim), "q99": torch.ones(dim)}
             for key, dim in (("observation.state", STATE_DIM), ("action", ACTION_DIM))}
    with pi05_tiny(folder):
        torch.manual_seed(seed)
        policy = PI05Policy(config)
        for part in (policy, *make_pi05_pre_post_processors(config, stats)):
            part.save_pretrained(folder)
    return folder
