"""The autoregressive (OpenVLA / RT-2 family) configuration."""

from __future__ import annotations

from dataclasses import dataclass

from vlactl.errors import check_choice
from vlactl.models.parts.config import VLAConfig

PROMPT_ATTENTIONS = ("causal", "bidirectional")
DECODES = ("argmax", "median")


@dataclass(frozen=True)
class AutoregressiveConfig(VLAConfig):
    INFERENCE_OPTIONS = ("decode",)
    # A short chunk decoded as chunk_size * 7 tokens: the prompt is read once per chunk, and executing a chunk
    # gives smoother motion than one action per query.
    chunk_size: int = 5
    replan_every: int = 5
    bins: int = 256  # uniform bins over the normalised action range [-1, 1] (OpenVLA)
    # How the prompt attends: "causal" (OpenVLA) or "bidirectional" within the prompt, the action tokens causal
    # after it (a prefix LM, as π0-FAST); decoding is token by token either way.
    prompt_attention: str = "causal"
    # Which bin each action token takes: the median of the predicted distribution (the bins are ordered; on
    # demonstration frames the median errs less than the mode, and closed loop it succeeds more: docs/models.md) or
    # the most likely one ("argmax", as OpenVLA decodes)
    decode: str = "median"

    def __post_init__(self):
        check_choice("model.prompt_attention", self.prompt_attention, PROMPT_ATTENTIONS)
        check_choice("model.decode", self.decode, DECODES)
