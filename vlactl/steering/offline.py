"""What the offline intervention stages (`vlactl sweep`, `vlactl controllability`) share: the policy and N frames
spread over a dataset, predictions under the same flow-matching noise, and batches of frames kept as parts that an
interrupted run resumes from (`vlactl.io.keyed_parts`)."""

from __future__ import annotations

import sys
from contextlib import nullcontext
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd
import torch
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from vlactl.config import resolve_path
from vlactl.io import atomic_write_parquet, keyed_parts
from vlactl.models.base import PolicyInput
from vlactl.steering.collect import model_frames, spread


def policy_and_frames(cfg: DictConfig, load_policy=None):
    """(vla, frames, rows, key): the policy, the dataset's frames as it reads them, the `cfg.frames` rows spread over
    them, and what any result over those rows depends on (the start of a `keyed_parts` key)."""
    from vlactl.models.registry import policy_loader, weights_fingerprint
    from vlactl.render_presets import warn_if_rendered_otherwise

    torch.set_num_threads(cfg.threads)
    vla = (load_policy or policy_loader(cfg))(str(cfg.model))
    warn_if_rendered_otherwise(str(cfg.model), vla, dataset=resolve_path(cfg.dataset))
    frames = model_frames(vla, resolve_path(cfg.dataset), resolve_path(cfg.cache_dir))
    key = {"model": str(cfg.model), "model_args": OmegaConf.to_container(cfg, resolve=True).get("model_args"),
           "weights": None if load_policy else weights_fingerprint(str(cfg.model)), "dataset": frames.fingerprint,
           "frames": cfg.frames, "batch_size": cfg.batch_size}
    return vla, frames, spread(len(frames), cfg.frames), key


def predict_chunk(vla, obs: PolicyInput, steering=None) -> np.ndarray:
    """The predicted action chunks [B, T, 7], inside `steering` (a context that installs hooks) if given. The policy
    is reset first, so every prediction of a batch draws the same noise and differences are the intervention's."""
    vla.reset()
    with torch.inference_mode(), steering or nullcontext():
        chunk = vla.predict_action_chunk(obs)
    return chunk.float().cpu().numpy()


def run_batches(out: Path, key: dict, results: tuple[str, ...], rows: np.ndarray, batch_size: int,
                work: Callable, desc: str, per_frame: int = 1) -> list[pd.DataFrame]:
    """Run `work(index, bar)` on each batch of `rows` not done yet; it returns one table per name in `results` and
    advances the progress bar by `per_frame` per frame. Each table is kept as a part (the first one last: it marks the
    batch done); returns each result over all batches."""
    parts = keyed_parts(out, key, results)
    starts = range(0, len(rows), batch_size)

    def part(start: int, i: int) -> Path:
        return parts / f"frames{start:06d}{'_' + Path(results[i]).stem if i else ''}.parquet"

    done = [start for start in starts if part(start, 0).is_file()]
    if done:
        print(f"resuming: {len(done)} of {len(starts)} batches of frames already done in {out}", file=sys.stderr)
    initial = sum(len(rows[start : start + batch_size]) for start in done) * per_frame
    with tqdm(total=len(rows) * per_frame, initial=initial, desc=desc, unit="frame") as bar:
        for start in (start for start in starts if start not in done):
            tables = work(rows[start : start + batch_size], bar)
            for i in reversed(range(len(results))):
                atomic_write_parquet(part(start, i), tables[i])
    return [pd.concat([pd.read_parquet(part(start, i)) for start in starts], ignore_index=True)
            for i in range(len(results))]
