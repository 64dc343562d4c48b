"""Hybrid VLA: a bidirectional Llama backbone over the prompt and a flow-matching action expert (π0's layout).

The backbone runs once per observation and leaves its per-layer keys/values in a `DynamicCache`; the expert, a
narrower Llama of the same depth, runs the action chunk as tokens whose layer i attends to [backbone layer-i K/V,
its own K/V]. Training: flow matching with x_t = t*noise + (1-t)*actions and target velocity noise - actions,
t ~ Beta(1.5, 1) (π0). Sampling: Euler steps from t=1 (noise) to t=0, the backbone cache reused at every step.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn
from transformers import DynamicCache, LlamaModel

from vlactl.models.base import episode_noise_seed
from vlactl.models.hybrid.configuration_hybrid import HybridConfig
from vlactl.models.hybrid.processor_hybrid import HybridProcessor
from vlactl.models.parts.policy import EmbeddedPolicy
from vlactl.models.parts.prefix import PrefixEmbedder, full_attention


def time_embedding(t: torch.Tensor, dim: int, min_period: float = 4e-3, max_period: float = 4.0) -> torch.Tensor:
    """Sinusoidal embedding of flow times in [0, 1] (π0's periods), [B] -> [B, dim]."""
    fraction = torch.linspace(0.0, 1.0, dim // 2)
    period = min_period * (max_period / min_period) ** fraction
    angle = t[:, None] * (2 * math.pi / period)[None]
    return torch.cat([angle.sin(), angle.cos()], dim=-1)


class HybridPolicy(EmbeddedPolicy):
    name = "hybrid"
    config_class = HybridConfig
    processor_class = HybridProcessor
    kv_source = "backbone"

    def __init__(self, config: HybridConfig, processor: HybridProcessor):
        super().__init__(config, processor)
        self.backbone = LlamaModel(config.llama_config(vocab_size=processor.vocab_size))
        self.prefix = PrefixEmbedder(config, self.backbone.embed_tokens)
        self.expert = LlamaModel(
            config.llama_config(hidden_size=config.expert_width, intermediate_size=config.expert_mlp_width)
        )
        self.expert.embed_tokens = None  # its inputs are action embeddings, not token ids (as SmolVLA's expert)
        width = config.expert_width
        self.action_in = nn.Linear(config.action_dim, width)
        self.action_time_mlp = nn.Sequential(nn.Linear(2 * width, width), nn.SiLU(), nn.Linear(width, width))
        self.action_out = nn.Linear(width, config.action_dim)
        self._noise = torch.Generator().manual_seed(config.noise_seed)
        self._row_noise: list[torch.Generator] | None = None  # predict_rows: one generator per batch row

    def _stacks(self):
        return {"backbone": self.backbone.layers, "expert": self.expert.layers}

    def reset(self, seed: int | None = None) -> None:
        self._noise.manual_seed(episode_noise_seed(self.config.noise_seed, seed))

    def sampling_state(self):
        return self._noise.get_state()

    def set_sampling_state(self, state) -> None:
        self._noise.set_state(state)

    def predict_rows(self, obs, states: list):
        """One forward; row i's noise drawn from its own generator, as `_sample` draws it for a batch of one."""
        self._row_noise = [torch.Generator() for _ in states]
        for generator, state in zip(self._row_noise, states):
            generator.set_state(state)
        try:
            chunk = self.predict_action_chunk(obs)
            return chunk, [g.get_state() for g in self._row_noise]
        finally:
            self._row_noise = None

    # --- the two halves -------------------------------------------------------------------------------------
    def _run_prefix(self, inputs) -> tuple[DynamicCache, int]:
        x, masks = self.prefix(inputs["images"], inputs["state"], inputs["tokens"], inputs["text_mask"])
        self._masks["backbone"] = masks
        b, t = x.shape[:2]
        cache = DynamicCache()
        self.backbone(inputs_embeds=x, attention_mask=full_attention(b, t, t), past_key_values=cache, use_cache=True)
        return cache, t

    def _velocity(self, cache: DynamicCache, n_prefix: int, noisy: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        b, s = noisy.shape[:2]
        width = self.config.expert_width
        time = time_embedding(t, width)[:, None].expand(-1, s, -1)
        x = self.action_time_mlp(torch.cat([self.action_in(noisy), time], dim=-1))
        suffix = torch.ones(b, s, dtype=torch.bool)
        last = torch.zeros(b, s, dtype=torch.bool)
        last[:, -1] = True
        none = torch.zeros(b, s, dtype=torch.bool)
        self._masks["expert"] = {"prefix": suffix, "last": last, "image": none, "text": none,
                                "action": suffix}
        positions = torch.arange(n_prefix, n_prefix + s)
        out = self.expert(
            inputs_embeds=x,
            attention_mask=full_attention(b, s, n_prefix + s),
            position_ids=positions[None].expand(b, -1),
            cache_position=positions,
            past_key_values=cache,
            use_cache=True,
        ).last_hidden_state
        cache.crop(n_prefix)  # drop the expert's own K/V so the next flow step sees only the backbone's
        return self.action_out(out)

    # --- training and inference ----------------------------------------------------------------------------
    def forward(self, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, float]]:
        actions = batch["actions"]
        b = actions.shape[0]
        noise = torch.randn_like(actions)
        t = torch.distributions.Beta(1.5, 1.0).sample((b,)) * 0.999 + 0.001
        noisy = t[:, None, None] * noise + (1 - t[:, None, None]) * actions
        cache, n_prefix = self._run_prefix(batch)
        error = F.mse_loss(self._velocity(cache, n_prefix, noisy, t), noise - actions, reduction="none")
        keep = (~batch["action_pad"]).float()[..., None].expand_as(error)
        loss = (error * keep).sum() / keep.sum().clamp(min=1)
        return loss, {"loss": loss.item()}

    def _sample(self, inputs) -> torch.Tensor:
        cache, n_prefix = self._run_prefix(inputs)
        b = inputs["state"].shape[0]
        shape = (self.config.chunk_size, self.config.action_dim)
        samples = self.config.samples
        if self._row_noise is None:
            x = torch.randn(b * samples, *shape, generator=self._noise)
        else:
            x = torch.cat([torch.randn(samples, *shape, generator=g) for g in self._row_noise])
        x = x * self.config.noise_scale
        if samples > 1:
            cache.batch_repeat_interleave(samples)
        steps = self.config.flow_steps
        for k in range(steps):
            t = torch.full((b * samples,), 1.0 - k / steps)
            x = x - self._velocity(cache, n_prefix, x, t) / steps
        # Several flows from independent noise: each action value the median of its samples (one value that
        # minimises the expected absolute error, as the autoregressive model's median bin).
        return x.view(b, samples, *shape).median(dim=1).values if samples > 1 else x

    def _encode(self, inputs) -> None:
        cache, n_prefix = self._run_prefix(inputs)
        b = inputs["state"].shape[0]
        zeros = torch.zeros(b, self.config.chunk_size, self.config.action_dim)
        self._velocity(cache, n_prefix, zeros, torch.full((b,), self.config.encode_time))
