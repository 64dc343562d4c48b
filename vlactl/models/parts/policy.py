"""What the two embedded models share: the VLA interface over named Llama layers, processing, and checkpoints.

A model subclass builds its modules, lists its layer stacks in `_stacks()`, records the read-out masks of the
forward it is running in `self._masks[stack]`, and implements `forward` (training loss), `_sample` (normalised
actions) and `_encode`.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import torch
from torch import nn

from vlactl.errors import UsageError
from vlactl.models.base import POOLINGS, PolicyInput, StackedLayers
from vlactl.models.parts.config import VLAConfig
from vlactl.models.parts.processing import Processor

WEIGHTS_FILE, CONFIG_FILE = "model.safetensors", "config.json"


class EmbeddedPolicy(nn.Module, StackedLayers):
    name = ""
    config_class = VLAConfig
    processor_class = Processor

    def __init__(self, config: VLAConfig, processor: Processor):
        nn.Module.__init__(self)
        self.config = config
        self.processor = processor
        self.chunk_size = config.chunk_size
        self.replan_every = config.replan_every
        self.gripper_levels = tuple(config.gripper_levels) or None
        self.cameras, self.image_size = tuple(config.cameras), config.image_size
        self._masks: dict[str, dict[str, torch.Tensor]] = {}

    # --- layers ---------------------------------------------------------------------------------------------
    def token_mask(self, name: str, pooling: str) -> torch.Tensor:
        if pooling not in POOLINGS:
            raise KeyError(f"unknown pooling {pooling!r}; allowed: {', '.join(POOLINGS)}")
        return self._masks[name.partition(".")[0]][pooling]

    def layer_width(self, name: str) -> int:
        return self.layer_module(name).hidden_size

    # --- running --------------------------------------------------------------------------------------------
    @torch.no_grad()
    def predict_action_chunk(self, obs: PolicyInput) -> torch.Tensor:
        return self.processor.unnormalize_actions(self._sample(self.processor.observation(obs)))

    @torch.no_grad()
    def encode(self, obs: PolicyInput) -> None:
        self._encode(self.processor.observation(obs))

    def reads_alike(self, a: str, b: str) -> bool:
        tokens, mask = self.processor.tokens([a, b])  # a word the tokenizer never saw is [UNK], whatever it was
        return torch.equal(tokens[0], tokens[1]) and torch.equal(mask[0], mask[1])

    def _sample(self, inputs: dict[str, torch.Tensor]) -> torch.Tensor:
        raise NotImplementedError

    def _encode(self, inputs: dict[str, torch.Tensor]) -> None:
        raise NotImplementedError

    # --- checkpoints ----------------------------------------------------------------------------------------
    def save_pretrained(self, folder: Path) -> None:
        """Weights, config and processor files into an existing folder (the caller makes the write atomic)."""
        from safetensors.torch import save_model

        from vlactl.io import atomic_write_json

        folder = Path(folder)
        save_model(self, str(folder / WEIGHTS_FILE))  # handles the text embedding the prefix shares with the decoder
        atomic_write_json(folder / CONFIG_FILE, {"model": self.name, "config": self.config.to_dict()})
        self.processor.save(folder)

    @classmethod
    def saved_config(cls, folder: Path) -> VLAConfig:
        """The config a checkpoint folder was saved with."""
        return cls.config_class.from_dict(json.loads((Path(folder) / CONFIG_FILE).read_text())["config"])

    @classmethod
    def from_pretrained(cls, folder: Path, **options) -> "EmbeddedPolicy":
        """The checkpoint in `folder`; `options` replace its config's `INFERENCE_OPTIONS` for this load."""
        from safetensors.torch import load_model

        folder = Path(folder)
        config = cls.saved_config(folder)
        allowed = cls.config_class.INFERENCE_OPTIONS
        if unknown := sorted(set(options) - set(allowed)):
            raise UsageError(f"model option {', '.join(f'model.{k}' for k in unknown)} does not apply to a {cls.name} "
                             f"checkpoint; allowed: {', '.join(f'model.{k}' for k in allowed) or 'none'}")
        config = dataclasses.replace(config, **options)
        policy = cls(config, cls.processor_class.load(config, folder))
        load_model(policy, str(folder / WEIGHTS_FILE))
        return policy.eval()


def read_model_name(folder: Path) -> str:
    return json.loads((Path(folder) / CONFIG_FILE).read_text())["model"]
