"""Autoregressive VLA (OpenVLA's layout): a causal Llama over [image tokens, text tokens, state token] that then
writes the action chunk as chunk_size * 7 tokens, one bin of one dimension each, greedily with a KV cache.

Action bins are tokens of the decoder's own vocabulary (after the words); the output head scores the bins only.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn
from transformers import DynamicCache, LlamaModel

from vlactl.models.autoregressive.configuration_autoregressive import AutoregressiveConfig
from vlactl.models.autoregressive.processor_autoregressive import AutoregressiveProcessor
from vlactl.models.parts.policy import EmbeddedPolicy
from vlactl.models.parts.prefix import PrefixEmbedder, decode_masks, full_attention, pad_masks, prefix_lm_attention


class AutoregressivePolicy(EmbeddedPolicy):
    name = "autoregressive"
    config_class = AutoregressiveConfig
    processor_class = AutoregressiveProcessor

    def __init__(self, config: AutoregressiveConfig, processor: AutoregressiveProcessor):
        super().__init__(config, processor)
        self.n_words = processor.vocab_size
        self.backbone = LlamaModel(config.llama_config(vocab_size=self.n_words + config.bins))
        self.prefix = PrefixEmbedder(config, self.backbone.embed_tokens)
        self.head = nn.Linear(config.width, config.bins, bias=False)
        self._written = 0  # the index in the chunk of the action token the forward now running writes

    @property
    def _prefix_lm(self) -> bool:
        return self.config.prompt_attention == "bidirectional"

    def _stacks(self):
        return {"backbone": self.backbone.layers}

    def written_dimension(self) -> int:
        return self._written % self.config.action_dim

    def _embed_bins(self, ids: torch.Tensor) -> torch.Tensor:
        return self.backbone.embed_tokens(ids + self.n_words)

    def _prompt(self, inputs) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        return self.prefix(inputs["images"], inputs["state"], inputs["tokens"], inputs["text_mask"])

    def forward(self, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, float]]:
        """Teacher forcing: the prompt and all action tokens but the last in; each action token predicted."""
        ids = batch["actions"].flatten(1)  # [B, chunk * 7]
        x, masks = self._prompt(batch)
        n_prompt = x.shape[1]
        self._masks["backbone"] = pad_masks(masks, ids.shape[1] - 1)
        x = torch.cat([x, self._embed_bins(ids[:, :-1])], 1)
        attention = prefix_lm_attention(x.shape[0], n_prompt, x.shape[1]) if self._prefix_lm else None
        h = self.backbone(inputs_embeds=x, attention_mask=attention).last_hidden_state
        logits = self.head(h[:, n_prompt - 1 :])
        nll = F.cross_entropy(logits.flatten(0, 1), ids.flatten(), reduction="none").view_as(ids)
        keep = (~batch["action_pad"]).float().repeat_interleave(self.config.action_dim, dim=1)
        loss = (nll * keep).sum() / keep.sum().clamp(min=1)
        accuracy = ((logits.argmax(-1) == ids).float() * keep).sum() / keep.sum().clamp(min=1)
        return loss, {"loss": loss.item(), "token_accuracy": accuracy.item()}

    def _prefill(self, inputs) -> tuple[torch.Tensor, DynamicCache]:
        x, masks = self._prompt(inputs)
        self._written = 0  # the prompt's last token writes the first action token
        self._masks["backbone"] = {**masks, "action": masks["last"]}
        cache = DynamicCache()
        attention = full_attention(x.shape[0], x.shape[1], x.shape[1]) if self._prefix_lm else None
        h = self.backbone(inputs_embeds=x, attention_mask=attention, past_key_values=cache, use_cache=True)
        h = h.last_hidden_state
        return h[:, -1], cache

    def _sample(self, inputs) -> torch.Tensor:
        h, cache = self._prefill(inputs)
        b = h.shape[0]
        self._masks["backbone"] = decode_masks(b)
        ids = []
        for k in range(self.config.chunk_size * self.config.action_dim):
            ids.append(self._pick(self.head(h)))
            if k + 1 < self.config.chunk_size * self.config.action_dim:
                self._written = k + 1
                step = self._embed_bins(ids[-1])[:, None]
                h = self.backbone(inputs_embeds=step, past_key_values=cache, use_cache=True).last_hidden_state[:, -1]
        chunk = torch.stack(ids, 1).view(b, self.config.chunk_size, self.config.action_dim)
        return self.processor.bin_centers(chunk)

    def predict_rows(self, obs, states: list):
        """Decoding draws no noise: the rows are one forward, their states unchanged."""
        return self.predict_action_chunk(obs), list(states)

    def _pick(self, logits: torch.Tensor) -> torch.Tensor:
        """[B, bins] -> the bin each row decodes to."""
        if self.config.decode == "median":
            return (logits.softmax(-1).cumsum(-1) < 0.5).sum(-1).clamp(max=self.config.bins - 1)
        return logits.argmax(-1)

    def _encode(self, inputs) -> None:
        self._prefill(inputs)

    def encode_actions(self, obs) -> None:
        self.predict_action_chunk(obs)
