"""Model names -> classes, imported only when asked for (LeRobot's factory style), and `load_policy`.

`load_policy` takes a checkpoint folder (written by `vlactl train-policy`), the name of an embedded model (its
default checkpoint folder, which must have been trained), the name of a real VLA's adapter with its options
(`model=pi05 model.checkpoint=<path or hub id>`; docs/real-models.md), or `random`: a tiny untrained model for
tests only.
"""

from __future__ import annotations

import functools
import importlib
from pathlib import Path

from vlactl.errors import UsageError

MODELS = {
    "hybrid": "vlactl.models.hybrid.modeling_hybrid:HybridPolicy",
    "autoregressive": "vlactl.models.autoregressive.modeling_autoregressive:AutoregressivePolicy",
}
# Real VLAs: adapters around the libraries' own classes, loaded from a user's checkpoint (never shipped).
ADAPTERS = {
    "smolvla": "vlactl.models.smolvla:SmolVLAAdapter",
    "pi05": "vlactl.models.pi05:PI05Adapter",
    "openvla": "vlactl.models.openvla:OpenVLAAdapter",
}
RANDOM = "random"
DEFAULT_RUN_DIR = "outputs/policies/{name}"  # where `vlactl train-policy model=<name>` writes by default
SHIPPED_DIR = "data/policies/{name}"  # the checkpoints that come with the repository (`make policies` rebuilds them)
CHECKPOINT_DIR = "checkpoint"  # inside a training run folder


def _import(target: str):
    module, _, cls = target.partition(":")
    return getattr(importlib.import_module(module), cls)


def policy_class(name: str):
    if name not in MODELS:
        raise UsageError(f"unknown model {name!r}; allowed: {', '.join(MODELS)}")
    return _import(MODELS[name])


def adapter_class(name: str):
    """A real VLA's adapter class (`ADAPTERS`)."""
    return _import(ADAPTERS[name])


def checkpoint_folder(path: Path) -> Path | None:
    """The checkpoint inside `path` (a checkpoint or a training run folder), or None."""
    from vlactl.models.parts.policy import CONFIG_FILE

    for folder in (path, path / CHECKPOINT_DIR):
        if (folder / CONFIG_FILE).is_file():
            return folder
    return None


def load_policy(name_or_path: str, **options):
    """The policy a model name or path stands for; `options` (`model.<option>=` overrides) go to a real model's
    adapter's `load`, or replace an embedded checkpoint's inference options (`VLAConfig.INFERENCE_OPTIONS`)."""
    from vlactl.models.parts.policy import read_model_name

    if name_or_path in ADAPTERS:
        return adapter_class(name_or_path).load(**options)
    if name_or_path == RANDOM:
        if options:
            raise UsageError(f"model options {', '.join(f'model.{k}' for k in options)} do not apply to {RANDOM!r}")
        return tiny_policy("hybrid")
    folder = resolve_checkpoint(name_or_path)
    return policy_class(read_model_name(folder)).from_pretrained(folder, **options)


def inference_options(name_or_path: str, **options) -> dict | None:
    """The inference options (`VLAConfig.INFERENCE_OPTIONS`) an embedded checkpoint acts with: its config's, as
    `options` (`model.<option>=`) replace them; None for a real model and `random`. A run records them, so that a
    resumed run acts as it began even when the checkpoint's own values changed."""
    from vlactl.models.parts.policy import read_model_name

    if name_or_path in ADAPTERS or name_or_path == RANDOM:
        return None
    folder = resolve_checkpoint(name_or_path)
    saved = policy_class(read_model_name(folder)).saved_config(folder)
    return {key: options.get(key, getattr(saved, key)) for key in saved.INFERENCE_OPTIONS}


def policy_loader(cfg):
    """`load_policy` with a stage config's real-model options (`cfg.model_args`) bound; picklable for workers."""
    from omegaconf import OmegaConf

    options = OmegaConf.to_container(cfg.model_args, resolve=True) if cfg.get("model_args") else {}
    return functools.partial(load_policy, **options) if options else load_policy


def resolve_checkpoint(name_or_path: str) -> Path:
    """The checkpoint folder a model name or path stands for. A name means the user's own training run if there is
    one (`vlactl train-policy model=<name>` writes it), else the shipped checkpoint."""
    from vlactl.config import resolve_path

    if name_or_path not in MODELS:
        path = resolve_path(name_or_path)
        folder = checkpoint_folder(path)
        if folder is None and path.is_dir():
            from vlactl.models.parts.policy import CONFIG_FILE

            raise UsageError(
                f"{name_or_path!r} is a folder but not a checkpoint (no {CONFIG_FILE} in it or in {CHECKPOINT_DIR}/); "
                "pass a folder written by `vlactl train-policy`, or a model name"
            )
        if folder is None:
            raise UsageError(
                f"unknown model {name_or_path!r}; allowed: {', '.join([*MODELS, *ADAPTERS])}, {RANDOM}, "
                "or a checkpoint path"
            )
        return folder
    places = [resolve_path(d.format(name=name_or_path)) for d in (DEFAULT_RUN_DIR, SHIPPED_DIR)]
    for place in places:
        if (folder := checkpoint_folder(place)) is not None:
            return folder
    raise UsageError(
        f"no trained {name_or_path} checkpoint in {places[0]} or {places[1]}; train one with "
        f"`vlactl train-policy model={name_or_path} dataset=<demos>` or pass a checkpoint path"
    )


def weights_fingerprint(name_or_path: str) -> str | None:
    """Hash of the weights a model name or checkpoint path stands for (None for real models and `random`): a resumed
    stage refuses outputs made by other weights, which a retrained checkpoint of the same name would be."""
    import hashlib

    from vlactl.models.parts.policy import WEIGHTS_FILE

    if name_or_path in ADAPTERS or name_or_path == RANDOM:
        return None
    return hashlib.sha256((resolve_checkpoint(name_or_path) / WEIGHTS_FILE).read_bytes()).hexdigest()[:16]


TINY = dict(
    vision_channels=(8, 8, 8), width=32, layers=2, heads=2, kv_heads=1, head_dim=16, mlp_width=64, max_text_tokens=12,
    chunk_size=4, replan_every=2,
)
TINY_EXTRA = {"hybrid": dict(expert_width=32, expert_mlp_width=64, flow_steps=2, samples=1), "autoregressive": {}}
TINY_INSTRUCTIONS = [
    "pick up the black bowl between the plate and the ramekin and place it on the plate",
    "pick up the black bowl on the stove and place it on the plate",
]


def tiny_policy(name: str, seed: int = 0, **overrides):
    """A tiny model with random weights and identity normalisation: a test fixture, never a default."""
    import numpy as np
    import torch

    cls = policy_class(name)
    config = cls.config_class(**{**TINY, **TINY_EXTRA[name], **overrides})
    box = np.array([[-1.0] * 8, [1.0] * 8])  # quantiles of +-1 give the identity normalisation
    processor = cls.processor_class.fit(config, TINY_INSTRUCTIONS, box.repeat(50, 0), box[:, :7].repeat(50, 0))
    torch.manual_seed(seed)
    return cls(config, processor).eval()
