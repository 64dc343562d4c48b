"""The prompt both model families read: [image tokens, text tokens, state token], and its read-out masks."""

from __future__ import annotations

import torch
from torch import nn

from vlactl.models.base import POOLINGS
from vlactl.models.parts.config import VLAConfig
from vlactl.models.parts.vision import ImageTokenizer


class PrefixEmbedder(nn.Module):
    def __init__(self, config: VLAConfig, text_embedding: nn.Embedding):
        super().__init__()
        width = text_embedding.embedding_dim
        self.vision = ImageTokenizer(
            len(config.cameras), config.vision_channels, width, config.image_size, config.image_tokens_side
        )
        self.text = text_embedding  # the decoder's own token embedding, as in a language model
        self.state = nn.Linear(config.state_dim, width)

    def forward(self, images, state, tokens, text_mask) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """Embeddings [B, T, width] and the bool [B, T] mask of each read-out set (base.POOLINGS)."""
        img = self.vision(images)
        x = torch.cat([img, self.text(tokens), self.state(state)[:, None]], dim=1)
        b, n_img, n_text = x.shape[0], img.shape[1], tokens.shape[1]
        segment = torch.zeros(x.shape[1], dtype=torch.long)
        segment[n_img : n_img + n_text] = 1
        segment[-1] = 2
        masks = {
            "prefix": torch.ones(b, x.shape[1], dtype=torch.bool),
            "image": (segment == 0).expand(b, -1),
            "text": torch.cat([torch.zeros(b, n_img, dtype=torch.bool), text_mask, torch.zeros(b, 1, dtype=torch.bool)], 1),
            "last": (segment == 2).expand(b, -1),
            "action": torch.zeros(b, x.shape[1], dtype=torch.bool),  # no prompt token is written as an action
        }
        return x, masks


def full_attention(batch: int, queries: int, keys: int) -> torch.Tensor:
    """An additive 4D mask that hides nothing: HF decoders take a 4D mask as is, so attention is bidirectional."""
    return torch.zeros(batch, 1, queries, keys)


def prefix_lm_attention(batch: int, prompt: int, tokens: int) -> torch.Tensor:
    """An additive 4D mask over `tokens` tokens of which the first `prompt` are the prompt: the prompt attends
    bidirectionally within itself, every later token causally (PaliGemma's prefix-LM, as π0-FAST decodes)."""
    allowed = torch.ones(tokens, tokens, dtype=torch.bool).tril()
    allowed[:prompt, :prompt] = True
    mask = torch.zeros(tokens, tokens).masked_fill(~allowed, torch.finfo(torch.float32).min)
    return mask.expand(batch, 1, tokens, tokens)


def pad_masks(masks: dict[str, torch.Tensor], extra: int) -> dict[str, torch.Tensor]:
    """Masks for a forward that runs `extra` tokens after the prompt: none of them is in any read-out set."""
    return {k: torch.cat([m, torch.zeros(m.shape[0], extra, dtype=torch.bool)], 1) for k, m in masks.items()}


def decode_masks(batch: int) -> dict[str, torch.Tensor]:
    """An autoregressive decode step's one token: in no prompt set, in the `action` set (it writes the next one)."""
    masks = {k: torch.zeros(batch, 1, dtype=torch.bool) for k in POOLINGS}
    masks["action"] = torch.ones(batch, 1, dtype=torch.bool)
    return masks
