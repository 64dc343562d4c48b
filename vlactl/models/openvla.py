"""OpenVLA (Hugging Face, `openvla/openvla-7b` and its LIBERO fine-tunes) behind the VLA interface:
`model=openvla model.checkpoint=<folder or hub id> model.unnorm_key=libero_spatial`.

OpenVLA is a Prismatic VLM: vision patches projected into a Llama-2 decoder, placed right after BOS, then the prompt
"In: What action should the robot take to {instruction}?\\nOut:". It emits each of the 7 action dimensions as one
token among the last 256 of the vocabulary, greedily; token id v means bin `vocab_size - v - 1` of 255 bin centres
over [-1, 1], un-normalised with the dataset's q01/q99 (`norm_stats[unnorm_key]`, dimensions whose mask is False -
the gripper - stay as they are). The gripper comes out as 0 = close / 1 = open and LIBERO wants -1 = open /
+1 = close, so it is binarised and inverted (OpenVLA's LIBERO evaluation does the same).

Layers: `backbone.i` are the Llama decoder layers. Read-out sets on the prompt forward (prefill): `image` the
projected patches, `text` BOS and the prompt, `prefix` both; the decode steps that emit action tokens hold none of
them (as the embedded autoregressive model). The modeling code lives on the hub (`trust_remote_code`); nothing here
imports it, so the same adapter runs any Hugging Face VLM laid out [BOS, patches, prompt] whose `generate` takes
`input_ids` and `pixel_values` (the tests use a tiny LLaVA).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
import transformers
import torch.nn.functional as F
from PIL import Image
from torch import nn

from vlactl.errors import UsageError
from vlactl.models.base import POOLINGS, PolicyInput, StackedLayers, last_true

PROMPT = "In: What action should the robot take to {instruction}?\nOut:"
EMPTY_TOKEN = 29871  # Llama-2's "▁": OpenVLA was trained with it before the action tokens and appends it if missing
ACTION_DIM, N_BINS = 7, 256
# OpenVLA's hub code under transformers >= 4.50 generates without ever running its vision tower (openvla/openvla#346):
# plausible, input-independent actions. Refuse rather than steer a blind model.
UNSEEN_IMAGE = (
    "openvla generated actions without running its vision tower (transformers {version}; openvla/openvla#346); "
    "use transformers==4.40.1 as the openvla extra installs (docs/real-models.md)"
)


def bin_centres(n_bins: int = N_BINS) -> np.ndarray:
    bins = np.linspace(-1.0, 1.0, n_bins)
    return (bins[:-1] + bins[1:]) / 2.0


def decode_actions(token_ids: np.ndarray, vocab_size: int, stats: dict) -> np.ndarray:
    """Action token ids [B, 7] -> actions [B, 7] in the dataset's units (OpenVLA's `predict_action`)."""
    centres = bin_centres()
    normalised = centres[np.clip(vocab_size - token_ids - 1, 0, len(centres) - 1)]
    low, high = np.asarray(stats["q01"]), np.asarray(stats["q99"])
    mask = np.asarray(stats.get("mask", np.ones_like(low, dtype=bool)))
    return np.where(mask, 0.5 * (normalised + 1) * (high - low) + low, normalised)


def to_libero_gripper(actions: np.ndarray) -> np.ndarray:
    """Gripper 0 = close / 1 = open -> LIBERO's +1 = close / -1 = open, binarised."""
    actions = actions.copy()
    actions[..., -1] = -np.sign(2 * actions[..., -1] - 1)
    return actions


def centre_crop(image: Image.Image, area: float = 0.9) -> Image.Image:
    """The crop OpenVLA's LIBERO fine-tunes saw at training (random crops of 90% area), taken at the centre."""
    side = np.sqrt(area)
    w, h = image.size
    cw, ch = w * side, h * side
    box = ((w - cw) / 2, (h - ch) / 2, (w + cw) / 2, (h + ch) / 2)
    return image.crop(box).resize((w, h), Image.BILINEAR)


class OpenVLAAdapter(StackedLayers):
    name = "openvla"
    chunk_size = replan_every = 1
    env_preset = "standard"  # its LIBERO fine-tunes were trained on LIBERO's own renders (vlactl.render_presets)

    def __init__(self, model, processor, norm_stats: dict, unnorm_key: str | None = None, prompt: str = PROMPT,
                 append_token: int | None = EMPTY_TOKEN, crop: bool = True):
        self.model, self.processor = model.eval(), processor
        keys = sorted(norm_stats)
        if unnorm_key is None and len(keys) == 1:
            unnorm_key = keys[0]
        if unnorm_key not in norm_stats:
            raise UsageError(f"model.unnorm_key={unnorm_key!r} is not in the checkpoint; allowed: {', '.join(keys)}")
        self.stats = norm_stats[unnorm_key]["action"]
        self.prompt, self.append_token, self.crop = prompt, append_token, crop
        text = model.config.text_config
        self.vocab_size = text.vocab_size - int(getattr(model.config, "pad_to_multiple_of", 0) or 0)
        self.device = next(model.parameters()).device
        self.dtype = next(model.parameters()).dtype
        self._masks: dict[str, torch.Tensor] = {}
        self._written = 0  # the action dimension the token of the pass now running writes
        self._image_tokens: int | None = None
        self.prompt_passes = 0  # forwards that ran the projected image: generate must make one per observation
        self._projector().register_forward_hook(self._count_image_tokens)
        self._decoder().register_forward_pre_hook(self._record_masks, with_kwargs=True)

    @classmethod
    def load(cls, checkpoint: str | None = None, unnorm_key: str | None = None, device: str | None = None,
             dtype: str | None = None, prompt: str = PROMPT, append_token: int | None = EMPTY_TOKEN,
             crop: bool = True) -> "OpenVLAAdapter":
        """From a local folder or hub id; bfloat16 on a GPU, float32 on the CPU unless `dtype` says otherwise."""
        from transformers import AutoModelForVision2Seq, AutoProcessor

        if not checkpoint:
            raise UsageError("model=openvla needs model.checkpoint=<local folder or hub id>")
        device = device or ("cuda" if torch.cuda.is_available() else "cpu")
        torch_dtype = getattr(torch, dtype) if dtype else (torch.bfloat16 if device.startswith("cuda") else torch.float32)
        try:
            processor = AutoProcessor.from_pretrained(checkpoint, trust_remote_code=True)
            # `torch_dtype`, not `dtype`: OpenVLA's hub code targets transformers 4.40, which knows only that name.
            model = AutoModelForVision2Seq.from_pretrained(checkpoint, torch_dtype=torch_dtype, trust_remote_code=True)
        except (OSError, ValueError) as exc:
            raise UsageError(f"cannot load openvla checkpoint {checkpoint!r}: {str(exc).splitlines()[0]}") from None
        norm_stats = getattr(model.config, "norm_stats", None)
        stats_file = Path(str(checkpoint)) / "dataset_statistics.json"
        if stats_file.is_file():  # fine-tunes write their statistics beside the weights
            norm_stats = {**(norm_stats or {}), **json.loads(stats_file.read_text())}
        if not norm_stats:
            raise UsageError(f"openvla checkpoint {checkpoint!r} has no norm_stats or dataset_statistics.json")
        return cls(model.to(device), processor, norm_stats, unnorm_key, prompt, append_token, crop)

    # --- layers -------------------------------------------------------------------------------------------------
    def _decoder(self) -> nn.Module:
        """The Llama stack: `language_model.model` in Prismatic (a causal LM), `language_model` in newer HF VLMs."""
        lm = self.model.language_model
        return lm.model if hasattr(lm, "model") and hasattr(lm.model, "layers") else lm

    def _projector(self) -> nn.Module:
        return getattr(self.model, "projector", None) or self.model.multi_modal_projector

    def _stacks(self) -> dict[str, nn.ModuleList]:
        return {"backbone": self._decoder().layers}

    def layer_width(self, name: str) -> int:
        return self.model.config.text_config.hidden_size

    def token_mask(self, name: str, pooling: str) -> torch.Tensor:
        if pooling not in POOLINGS:
            raise KeyError(f"unknown pooling {pooling!r}; allowed: {', '.join(POOLINGS)}")
        self.layer_module(name)
        return self._masks[pooling]

    def written_dimension(self) -> int:
        return self._written

    def _count_image_tokens(self, module, args, output) -> None:
        self._image_tokens = output.shape[1]

    def _record_masks(self, module, args, kwargs) -> None:
        """Before each pass through the decoder: the prompt pass (patches were just projected) or a decode step."""
        tokens = kwargs.get("inputs_embeds")
        tokens = kwargs.get("input_ids") if tokens is None else tokens  # Prismatic's decode steps pass ids
        (b, t), device = tokens.shape[:2], tokens.device
        attention = kwargs.get("attention_mask")
        valid = attention[:, -t:].bool() if attention is not None and attention.dim() == 2 else \
            torch.ones(b, t, dtype=torch.bool, device=device)
        if self._image_tokens is None:  # a decode step: no prompt tokens, each one writes the next action token
            self._written += 1
            self._masks = {**dict.fromkeys(POOLINGS, torch.zeros(b, t, dtype=torch.bool, device=device)),
                           "action": valid}
            return
        self.prompt_passes += 1
        self._written = 0
        positions = torch.arange(t, device=device)
        image = valid & (positions >= 1) & (positions < 1 + self._image_tokens)
        last = last_true(valid)
        self._masks = {"prefix": valid, "last": last, "image": image, "text": valid & ~image, "action": last}
        self._image_tokens = None

    # --- running ------------------------------------------------------------------------------------------------
    def _inputs(self, obs: PolicyInput, index: slice) -> dict:
        """Prompts tokenised one by one (each ends with the empty token) and right-padded: Prismatic puts the
        patches after the first token of each row, so left padding would misplace them."""
        rows = []
        for array, text in zip(obs.images["image"][index], obs.instruction[index]):
            image = Image.fromarray(np.asarray(array))
            one = self.processor(text=self.prompt.format(instruction=text.lower()),
                                 images=centre_crop(image) if self.crop else image, return_tensors="pt")
            ids = one["input_ids"][0]
            if self.append_token is not None and int(ids[-1]) != self.append_token:
                ids = torch.cat([ids, torch.tensor([self.append_token])])
            rows.append((ids, one["pixel_values"][0]))
        length = max(len(ids) for ids, _ in rows)
        pad = self.processor.tokenizer.pad_token_id or 0
        return {
            "input_ids": torch.stack([F.pad(ids, (0, length - len(ids)), value=pad) for ids, _ in rows]).to(self.device),
            "attention_mask": torch.stack([torch.arange(length) < len(ids) for ids, _ in rows]).long().to(self.device),
            "pixel_values": torch.stack([pixels for _, pixels in rows]).to(self.device, self.dtype),
        }

    @torch.no_grad()
    def predict_action_chunk(self, obs: PolicyInput) -> torch.Tensor:
        """One observation at a time: greedy decoding of padded prompts would shift the action tokens."""
        actions = []
        for i in range(len(obs.instruction)):
            inputs = self._inputs(obs, slice(i, i + 1))
            passes = self.prompt_passes
            ids = self.model.generate(**inputs, max_new_tokens=ACTION_DIM, do_sample=False)
            if self.prompt_passes == passes:
                raise UsageError(UNSEEN_IMAGE.format(version=transformers.__version__))
            tokens = ids[:, -ACTION_DIM:].cpu().numpy()
            actions.append(to_libero_gripper(decode_actions(tokens, self.vocab_size, self.stats)))
        return torch.from_numpy(np.concatenate(actions)).float()[:, None]

    @torch.no_grad()
    def encode(self, obs: PolicyInput) -> None:
        """The prompt forward only (prefill), batched."""
        self.model(**self._inputs(obs, slice(None)))

    def encode_actions(self, obs: PolicyInput) -> None:
        """The prediction itself (a prefill and the decode steps, one observation at a time): slower than `encode`."""
        self.predict_action_chunk(obs)
