"""Train an embedded VLA on a demonstration dataset: AdamW, warm-up + cosine schedule, periodic checkpoints, exact
resume (weights, optimizer, schedule, step and every RNG are saved together), provenance in the checkpoint.

Run folder (`output_dir`): `checkpoint/` (the policy: what `load_policy` reads; replaced atomically at each save),
`training_state.pt` (what resuming needs), `config.yaml` (the resolved config).
"""

from __future__ import annotations

import math
import random
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from vlactl.config import resolve_path, save_config
from vlactl.errors import UsageError, check_non_negative, check_positive
from vlactl.io import atomic_dir, atomic_path, atomic_write_json, ensure_writable_dir
from vlactl.models.registry import CHECKPOINT_DIR, policy_class

STATE_FILE = "training_state.pt"


def warmup_cosine(warmup: int, total: int, floor: float):
    """LR factor: linear warm-up, then cosine decay to `floor` at the last step."""

    def factor(step: int) -> float:
        if step < warmup:
            return (step + 1) / warmup
        progress = min(1.0, (step - warmup) / max(1, total - warmup))
        return floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * progress))

    return factor


def _check(cfg: DictConfig) -> None:
    for key in ("steps", "batch_size", "lr", "save_every", "log_every", "threads"):
        check_positive(key, cfg[key])
    for key in ("warmup_steps", "augment_shift", "weight_decay"):
        check_non_negative(key, cfg[key])


def _rng_state() -> dict:
    return {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}


def _set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])


class Run:
    """The run's mutable state and how it is saved: the checkpoint first, then the state that points past it."""

    def __init__(self, cfg: DictConfig, out: Path, dataset: Path, frames, policy, optimizer, scheduler):
        self.cfg, self.out, self.dataset, self.frames = cfg, out, dataset, frames
        self.policy, self.optimizer, self.scheduler = policy, optimizer, scheduler
        self.step, self.curve, self.train_s = 0, [], 0.0

    def save(self) -> None:
        from vlactl.render_presets import dataset_env
        from vlactl.training.provenance import environment, git_commit

        with atomic_dir(self.out / CHECKPOINT_DIR) as tmp:
            self.policy.save_pretrained(tmp)
            atomic_write_json(tmp / "provenance.json", {
                "dataset": str(self.dataset),
                "dataset_fingerprint": self.frames.fingerprint,
                "dataset_frames": len(self.frames),
                "dataset_episodes": int(self.frames.episode.max()) + 1,
                "env": dataset_env(self.dataset),  # how its images were rendered: stages warn when theirs differ
                "step": self.step,
                "seed": self.cfg.seed,
                "git_commit": git_commit(),
                "train_wall_s": round(self.train_s, 1),
                "config": OmegaConf.to_container(self.cfg, resolve=True),
                "environment": environment(),
                "curve": self.curve,
            })
        with atomic_path(self.out / STATE_FILE) as tmp:
            torch.save({
                "model": self.policy.state_dict(),
                "optimizer": self.optimizer.state_dict(),
                "scheduler": self.scheduler.state_dict(),
                "step": self.step,
                "curve": self.curve,
                "train_s": self.train_s,
                "rng": _rng_state(),
                "dataset_fingerprint": self.frames.fingerprint,
                "model_config": OmegaConf.to_container(self.cfg.model, resolve=True),
            }, tmp)

    def resume(self) -> None:
        state = torch.load(self.out / STATE_FILE, weights_only=False)  # our own file: holds NumPy RNG state
        if state["dataset_fingerprint"] != self.frames.fingerprint or state["model_config"] != OmegaConf.to_container(
            self.cfg.model, resolve=True
        ):
            raise UsageError(
                f"{self.out} holds a run with another dataset or model config; "
                "choose another output_dir=... or start over with resume=false"
            )
        self.policy.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        self.step, self.curve, self.train_s = state["step"], state["curve"], state["train_s"]
        _set_rng_state(state["rng"])


def _starting_policy(cls, config, init_from: str):
    """The checkpoint a fine-tuning run starts from, rebuilt with the run's config and the checkpoint's weights and
    normalisation. Settings that leave every weight's shape alone (how the prompt attends, chunk length, gripper
    levels) may differ from the checkpoint's; the architecture may not."""
    from vlactl.models.registry import resolve_checkpoint

    start = cls.from_pretrained(resolve_checkpoint(init_from))
    policy = cls(config, cls.processor_class(config, start.processor.tokenizer, start.processor.stats))
    try:
        policy.load_state_dict(start.state_dict())
    except RuntimeError:  # missing, unexpected or differently shaped weights
        raise UsageError(f"init_from={init_from!r} is a different {cls.name} architecture than model={cls.name} "
                         "(conf/model/); train from scratch or override the model fields to match") from None
    return policy


def run_train_policy(cfg: DictConfig) -> Path:
    """Train (or resume) and return the checkpoint folder."""
    from tqdm import tqdm

    from vlactl.data.frames import load_frames
    from vlactl.training.batches import BatchSampler

    _check(cfg)
    torch.set_num_threads(cfg.threads)  # deliberate: on 2 shared cores, oversubscribing threads is many times slower
    dataset = resolve_path(cfg.dataset)
    out = ensure_writable_dir(resolve_path(cfg.output_dir), cfg.output_dir)
    cls = policy_class(cfg.model.name)
    config = cls.config_class.from_dict({k: v for k, v in OmegaConf.to_container(cfg.model).items() if k != "name"})
    frames = load_frames(dataset, config.cameras, resolve_path(cfg.cache_dir), config.image_size, config.state_dim)
    resuming = bool(cfg.resume) and (out / STATE_FILE).exists()

    random.seed(cfg.seed)
    np.random.seed(cfg.seed)
    torch.manual_seed(cfg.seed)
    start = None if resuming or not cfg.init_from else _starting_policy(cls, config, str(cfg.init_from))
    if start is not None:  # fine-tuning keeps the normalisation the weights were trained with
        policy = start
    elif resuming:
        policy = cls(config, cls.processor_class.load(config, out / CHECKPOINT_DIR))
    else:
        instructions = [frames.tasks[t] for t in np.unique(frames.task)]
        policy = cls(config, cls.processor_class.fit(config, instructions, frames.state, frames.action))
    processor = policy.processor
    optimizer = torch.optim.AdamW(policy.parameters(), lr=cfg.lr, betas=(0.9, 0.95), weight_decay=cfg.weight_decay)
    scheduler = torch.optim.lr_scheduler.LambdaLR(
        optimizer, warmup_cosine(cfg.warmup_steps, cfg.steps, cfg.min_lr_ratio)
    )
    run = Run(cfg, out, dataset, frames, policy, optimizer, scheduler)
    if resuming:
        run.resume()
    else:
        save_config(cfg, out)
        run.save()  # step 0: the processor is on disk from the start, so a resume never re-fits it
    sample = BatchSampler(frames, processor, cfg.batch_size, cfg.augment_shift)

    policy.train()
    pending: list[dict] = []
    with tqdm(total=cfg.steps, initial=run.step, desc=f"train {cls.name}", unit="step", dynamic_ncols=True) as bar:
        while run.step < cfg.steps:
            start = time.perf_counter()
            loss, metrics = policy(sample())
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(policy.parameters(), cfg.grad_clip)
            optimizer.step()
            scheduler.step()
            run.step += 1
            run.train_s += time.perf_counter() - start
            pending.append(metrics)
            saving = run.step % cfg.save_every == 0 or run.step == cfg.steps
            if run.step % cfg.log_every == 0 or saving:
                point = {k: float(np.mean([m[k] for m in pending])) for k in pending[0]}
                run.curve.append({"step": run.step, **point, "lr": scheduler.get_last_lr()[0], "train_s": run.train_s})
                bar.set_postfix({k: f"{v:.4f}" for k, v in point.items()})
                pending = []
            if saving:
                run.save()
            bar.update(1)
    return out / CHECKPOINT_DIR
