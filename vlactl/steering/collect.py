"""`vlactl collect`: run a policy over the frames of a LeRobot dataset and store every chosen layer's pooled
representation beside the frame's robot labels (the paper's Algorithm 1), for `vlactl train-probes`.

Frames go through the model in batches of whole episodes; each finished group of episodes is handed to the
`ActivationWriter`, which commits whole shards. Memory therefore holds one group and one shard whatever the dataset's
size (images come from the memory-mapped cache), and a re-run skips the episodes already committed.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from vlactl.config import REPO_ROOT, resolve_path, save_config
from vlactl.data.frames import Frames, load_frames, read_columns
from vlactl.data.lerobot_format import ACTION_KEY, ROBOT_STATE_KEY
from vlactl.env.features import ACTION_FEATURES, STATE_FEATURES, robot_state_from_libero, speeds
from vlactl.errors import UsageError, check_choice, check_positive
from vlactl.io import ensure_writable_dir
from vlactl.memory import fix_mmap_threshold, release_free_memory
from vlactl.models.base import POOLINGS, PolicyInput
from vlactl.models.hooks import capture
from vlactl.steering.activations import DTYPES, ActivationWriter


def _check(cfg: DictConfig) -> None:
    if OmegaConf.is_missing(cfg, "model"):
        raise UsageError("which model? pass model=<registry name or checkpoint folder>, e.g. model=hybrid")
    check_choice("pooling", cfg.pooling, POOLINGS)
    check_choice("dtype", cfg.dtype, DTYPES)
    for key in ("every", "batch_size", "shard_size", "threads"):
        check_positive(key, cfg[key])
    if cfg.max_episodes is not None:
        check_positive("max_episodes", cfg.max_episodes)


def choose_layers(vla, chosen) -> list[str]:
    available = vla.layer_names()
    if chosen == "all":
        return available
    chosen = [chosen] if isinstance(chosen, str) else list(chosen)
    unknown = [name for name in chosen if name not in available]
    if unknown or not chosen:
        raise UsageError(f"unknown layer {unknown[0] if unknown else chosen!r}; allowed: all, {', '.join(available)}")
    return chosen


def frame_labels(root: Path, frames: Frames) -> pd.DataFrame:
    """Per frame: episode, frame index, task, init state, instruction and the SPEC.md §2 features.

    Datasets written by `vlactl demos` carry the robot features and speed; for any other LIBERO dataset they are
    derived from the 8-D state (and speed from consecutive positions), which gives the same values.
    """
    features = json.loads((root / "meta" / "info.json").read_text())["features"]
    optional = [key for key in (ROBOT_STATE_KEY, "speed", "init_state") if key in features]
    columns = read_columns(root, ["frame_index", *optional])
    state = columns[ROBOT_STATE_KEY] if ROBOT_STATE_KEY in columns else robot_state_from_libero(frames.state)
    if "speed" in columns:
        speed = columns["speed"].reshape(-1)
    else:
        speed = np.concatenate([speeds(state[frames.episode == e, :3]) for e in pd.unique(frames.episode)])
    labels = pd.DataFrame({
        "episode": frames.episode,
        "frame_index": columns["frame_index"].reshape(-1).astype(np.int64),
        "task_id": frames.task,
        "init_state": columns["init_state"].reshape(-1).astype(np.int64) if "init_state" in columns else -1,
        "instruction": np.asarray(frames.tasks, dtype=object)[frames.task],
    })
    for i, name in enumerate(STATE_FEATURES):
        labels[name] = state[:, i].astype(np.float32)
    for i, name in enumerate(ACTION_FEATURES):
        labels[name] = frames.action[:, i]
    labels["speed"] = speed.astype(np.float32)
    return labels


def _groups(episodes: np.ndarray, rows: np.ndarray, batch_size: int):
    """Rows split into groups of whole episodes of at least `batch_size` frames (the last group may be smaller)."""
    group: list[np.ndarray] = []
    count = 0
    for episode in pd.unique(episodes[rows]):
        group.append(rows[episodes[rows] == episode])
        count += len(group[-1])
        if count >= batch_size:
            yield np.concatenate(group)
            group, count = [], 0
    if group:
        yield np.concatenate(group)


def model_frames(vla, root: Path, cache_dir: Path) -> Frames:
    """A dataset's frames as this model reads them: its cameras, at its image size (collect, sweep, plot readings)."""
    return load_frames(root, tuple(vla.cameras), cache_dir, image_size=vla.image_size)


def frame_batch(frames: Frames, index: np.ndarray) -> PolicyInput:
    """Dataset frames as one policy input (images from the cache, LIBERO state, instructions)."""
    images = frames.images_at(index)
    return PolicyInput(images={cam: images[:, k] for k, cam in enumerate(frames.cameras)}, state=frames.state[index],
                       instruction=[frames.tasks[t] for t in frames.task[index]])


def spread(n_frames: int, n: int) -> np.ndarray:
    """About n frame indices spread evenly over a dataset of n_frames (all of them if n >= n_frames)."""
    return np.unique(np.linspace(0, n_frames - 1, min(n, n_frames)).round().astype(int))


def pooled_activations(vla, layers: list[str], pooling: str, obs: PolicyInput) -> dict[str, np.ndarray]:
    """One `encode` of a batch (`encode_actions` for the `action` set) with every chosen layer captured: layer ->
    [B, width] float32, the mean over the forwards that read the set (an autoregressive model's `action` set: one
    position a forward, the prompt's last token and each decode step; every other set: one forward)."""
    with capture(vla, layers, pooling) as readings, torch.inference_mode():
        vla.encode_for(obs, pooling)
    empty = [name for name in layers if not readings[name]]
    if empty:
        raise UsageError(
            f"layer {empty[0]} has no tokens in the read-out set {pooling!r} (an action expert's layers have no "
            f"image or text tokens, a hybrid's backbone no action tokens); choose pooling=prefix or pooling=last, "
            f"or other layers"
        )
    return {name: torch.stack(readings[name]).mean(0).float().cpu().numpy() for name in layers}


def default_output(cfg: DictConfig) -> Path:
    model, dataset = Path(str(cfg.model)).name, resolve_path(cfg.dataset).name
    return REPO_ROOT / "outputs" / "activations" / f"{model}_{dataset}_{cfg.pooling}"


def run_collect(cfg: DictConfig, load_policy=None) -> Path:
    """Collect (or resume collecting) and return the activation folder. `load_policy` replaces the registry."""
    from vlactl.models.registry import policy_loader, weights_fingerprint

    _check(cfg)
    torch.set_num_threads(cfg.threads)
    fix_mmap_threshold()
    vla = (load_policy or policy_loader(cfg))(str(cfg.model))
    from vlactl.render_presets import warn_if_rendered_otherwise
    warn_if_rendered_otherwise(str(cfg.model), vla, dataset=resolve_path(cfg.dataset))
    layers = choose_layers(vla, cfg.layers)
    root = resolve_path(cfg.dataset)
    out = ensure_writable_dir(resolve_path(cfg.output_dir) if cfg.output_dir else default_output(cfg), cfg.output_dir)
    frames = model_frames(vla, root, resolve_path(cfg.cache_dir))
    labels = frame_labels(root, frames)

    keep = labels["frame_index"].to_numpy() % cfg.every == 0
    if cfg.max_episodes is not None:
        keep &= np.isin(frames.episode, pd.unique(frames.episode)[: cfg.max_episodes])
    info = {"dataset": str(root), "dataset_fingerprint": frames.fingerprint, "every": cfg.every,
            "max_episodes": cfg.max_episodes, "checkpoint": str(cfg.model), "steerable_layers": vla.steerable_layers(),
            "weights": None if load_policy else weights_fingerprint(str(cfg.model))}
    with ActivationWriter(
        out, model=vla.name, layers=layers, widths={name: vla.layer_width(name) for name in layers},
        pooling=cfg.pooling, dtype=cfg.dtype, shard_size=cfg.shard_size, info=info,
    ) as writer:
        if writer.meta["info"].get("dataset_fingerprint") != frames.fingerprint:
            raise UsageError(f"{str(out)!r} holds activations of another dataset; choose another output_dir=...")
        if writer.meta["info"].get("weights", info["weights"]) != info["weights"]:
            raise UsageError(f"{str(out)!r} holds activations of other weights of {cfg.model!r} (retrained?); "
                             "choose another output_dir=...")
        save_config(cfg, out)
        keep &= ~np.isin(frames.episode, list(writer.episodes()))
        rows = np.flatnonzero(keep)
        total = int(keep.sum()) + writer.n_frames
        with tqdm(total=total, initial=writer.n_frames, desc=f"collect {vla.name}", unit="frame") as bar:
            for group in _groups(frames.episode, rows, cfg.batch_size):
                pieces = []
                for start in range(0, len(group), cfg.batch_size):
                    index = group[start : start + cfg.batch_size]
                    pieces.append(pooled_activations(vla, layers, cfg.pooling, frame_batch(frames, index)))
                    bar.update(len(index))
                writer.append({name: np.concatenate([p[name] for p in pieces]) for name in layers}, labels.iloc[group])
                release_free_memory()
    print(f"wrote {writer.n_frames} frames x {len(layers)} layers to {out}", file=sys.stderr)
    return out
