"""Fields every embedded model shares: what it sees (cameras, text, state), what it outputs, its backbone's shape."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import ClassVar


@dataclass(frozen=True)
class VLAConfig:
    # Fields that change how a trained model acts, not its weights: a stage may set them for one run
    # (`model.<field>=<value>`) on a checkpoint that was saved with other values.
    INFERENCE_OPTIONS: ClassVar[tuple[str, ...]] = ()
    cameras: tuple[str, ...] = ("image", "wrist_image")
    image_size: int = 128
    vision_channels: tuple[int, ...] = (16, 32, 64)
    image_tokens_side: int = 4  # tokens per camera = side**2
    max_text_tokens: int = 20  # LIBERO instructions have <= 17 words
    state_dim: int = 8
    action_dim: int = 7
    chunk_size: int = 10
    replan_every: int = 5
    gripper_levels: tuple[float, ...] = (-1.0, 0.0, 1.0)  # the expert's: open, hold, close (empty: as predicted)
    # backbone (a Llama decoder)
    width: int = 128
    layers: int = 6
    heads: int = 4
    kv_heads: int = 2
    head_dim: int = 32
    mlp_width: int = 384

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "VLAConfig":
        """Lists (JSON, YAML) become tuples so the config stays hashable; unknown keys are an error."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown {cls.__name__} fields: {sorted(unknown)}")
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})

    def prefix_tokens(self) -> int:
        return len(self.cameras) * self.image_tokens_side**2 + self.max_text_tokens + 1

    def llama_config(self, **overrides):
        from transformers import LlamaConfig

        kwargs = dict(
            hidden_size=self.width,
            intermediate_size=self.mlp_width,
            num_hidden_layers=self.layers,
            num_attention_heads=self.heads,
            num_key_value_heads=self.kv_heads,
            head_dim=self.head_dim,
            max_position_embeddings=512,
            vocab_size=1,
            attn_implementation="sdpa",
        )
        kwargs.update(overrides)
        return LlamaConfig(**kwargs)
