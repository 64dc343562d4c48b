"""Pre- and post-processing shared by the embedded models: observations in, normalised tensors out, and back.

Each model's `processor_<name>.py` adds only how it represents actions (floats for flow matching, bins for tokens).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from vlactl.models.base import PolicyInput
from vlactl.models.parts.config import VLAConfig
from vlactl.models.parts.normalize import Normalizer, load_stats, save_stats
from vlactl.models.parts.text import encode, load_tokenizer, train_tokenizer

TOKENIZER_FILE, STATS_FILE = "tokenizer.json", "normalization.json"


class Processor:
    def __init__(self, config: VLAConfig, tokenizer, stats: dict[str, Normalizer]):
        self.config = config
        self.tokenizer = tokenizer
        self.stats = stats

    @classmethod
    def fit(cls, config: VLAConfig, instructions: list[str], states: np.ndarray, actions: np.ndarray) -> "Processor":
        """Tokenizer and normalisation statistics from the training data."""
        stats = {"state": Normalizer.fit(states), "action": Normalizer.fit(actions)}
        return cls(config, train_tokenizer(sorted(set(instructions))), stats)

    def save(self, folder: Path) -> None:
        self.tokenizer.save(str(Path(folder) / TOKENIZER_FILE))
        save_stats(Path(folder) / STATS_FILE, self.stats)

    @classmethod
    def load(cls, config: VLAConfig, folder: Path) -> "Processor":
        return cls(config, load_tokenizer(Path(folder) / TOKENIZER_FILE), load_stats(Path(folder) / STATS_FILE))

    @property
    def vocab_size(self) -> int:
        return self.tokenizer.get_vocab_size()

    # --- steps ---------------------------------------------------------------------------------------------
    def images(self, frames) -> torch.Tensor:
        """uint8 [B, cams, H, W, 3] -> float [B, cams, 3, H, W] in [0, 1]."""
        x = torch.as_tensor(frames)
        size = self.config.image_size
        if x.dtype != torch.uint8 or tuple(x.shape[-3:]) != (size, size, 3):
            raise ValueError(f"expected uint8 images [..., {size}, {size}, 3], got {x.dtype} {tuple(x.shape)}")
        return x.permute(0, 1, 4, 2, 3).float().div_(255)

    def state(self, state) -> torch.Tensor:
        return self.stats["state"](torch.as_tensor(state, dtype=torch.float32))

    def tokens(self, instructions: list[str]) -> tuple[torch.Tensor, torch.Tensor]:
        return encode(self.tokenizer, instructions, self.config.max_text_tokens)

    def observation(self, obs: PolicyInput) -> dict[str, torch.Tensor]:
        images = np.stack([obs.images[cam] for cam in self.config.cameras], axis=1)
        tokens, text_mask = self.tokens(list(obs.instruction))
        return {"images": self.images(images), "state": self.state(obs.state), "tokens": tokens, "text_mask": text_mask}

    def actions(self, actions: torch.Tensor) -> torch.Tensor:
        """Raw actions [B, chunk, 7] -> the model's training targets."""
        raise NotImplementedError

    def unnormalize_actions(self, x: torch.Tensor) -> torch.Tensor:
        """Normalised actions -> LIBERO's action space, clipped to its [-1, 1] box."""
        return self.stats["action"].inverse(x).clamp(-1.0, 1.0)
