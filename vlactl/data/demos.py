"""`vlactl demos`: scripted-expert demonstrations, generated in worker processes, written as a LeRobot dataset.

Two phases, so an interruption never leaves a half-written episode and a re-run resumes where it stopped:
1. each episode runs in a worker and is saved atomically to `<output_dir>.staging/` (successes as .npz, failures
   as a small .json), skipped on re-run if already there;
2. the LeRobot v3 dataset is built from the staged successes into a sibling folder and renamed into place.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from vlactl.config import resolve_path, save_config
from vlactl.errors import UsageError, check_choice, check_non_negative, check_positive
from vlactl.io import atomic_path, atomic_write_json, ensure_writable_dir

SUMMARY_NAME = "vlactl_demos.json"
RECOVERY_SEED = 100_000  # recovery episodes' seeds start here, apart from the normal episodes'


def _episode_stem(staging: Path, task: int, k: int, recovery: bool = False) -> Path:
    return staging / f"task{task:02d}" / f"{'rec' if recovery else 'ep'}{k:04d}"


def _done(staging: Path, task: int, k: int, recovery: bool) -> bool:
    stem = _episode_stem(staging, task, k, recovery)
    return stem.with_suffix(".npz").exists() or stem.with_suffix(".json").exists()


def run_demos(cfg: DictConfig) -> dict:
    from vlactl.env.suites import SUITES, resolve_tasks

    check_choice("suite", cfg.suite, SUITES)
    check_non_negative("episodes_per_task", cfg.episodes_per_task)
    check_non_negative("recovery_episodes_per_task", cfg.recovery_episodes_per_task)
    check_positive("workers", cfg.workers)
    tasks = resolve_tasks(cfg.suite, cfg.tasks)
    out = resolve_path(cfg.output_dir)
    ensure_writable_dir(out.parent, requested=out)
    staging = ensure_writable_dir(out.with_name(out.name + ".staging"))
    save_config(cfg, staging)

    kinds = [(False, cfg.episodes_per_task, cfg.seed), (True, cfg.recovery_episodes_per_task, cfg.seed + RECOVERY_SEED)]
    everything = [(t, k, rec, seed + k) for rec, n, seed in kinds for t in tasks for k in range(n)]
    env_cfg = OmegaConf.to_container(cfg.env, resolve=True)
    work = [(cfg.suite, t, k, rec, seed, env_cfg, str(staging))
            for t, k, rec, seed in everything if not _done(staging, t, k, rec)]
    total = len(everything)
    bar = tqdm(total=total, initial=total - len(work), desc=f"demos {cfg.suite}", unit="ep")
    if work:
        ctx = mp.get_context("spawn")
        with ctx.Pool(min(cfg.workers, len(work)), initializer=_worker_init) as pool:
            for ok in pool.imap_unordered(_generate_episode, work):
                bar.update(1)
                bar.set_postfix_str("ok" if ok else "expert failed")
    bar.close()

    summary = summarise(staging, cfg.suite, tasks, cfg.episodes_per_task)
    if cfg.recovery_episodes_per_task:
        summary["recovery"] = summarise(staging, cfg.suite, tasks, cfg.recovery_episodes_per_task, recovery=True)
    episodes = sorted(
        stem.with_suffix(".npz")
        for t, k, rec, _ in everything
        if (stem := _episode_stem(staging, t, k, rec)).with_suffix(".npz").exists()
    )
    from vlactl.data.lerobot_format import write_dataset

    with tqdm(total=len(episodes), desc="writing LeRobot dataset", unit="ep") as wbar:
        write_dataset(out, f"vlactl/{cfg.suite}", cfg.fps, cfg.env.image_size, (_load(p) for p in episodes), wbar)
    atomic_write_json(out / "meta" / SUMMARY_NAME, {"config": OmegaConf.to_container(cfg), **summary})
    save_config(cfg, out)
    _print_summary(summary)
    return summary


def summarise(staging: Path, suite: str, tasks: list[int], per_task: int, recovery: bool = False) -> dict:
    rows = {}
    for t in tasks:
        ok = sum(_episode_stem(staging, t, k, recovery).with_suffix(".npz").exists() for k in range(per_task))
        failed = sum(_episode_stem(staging, t, k, recovery).with_suffix(".json").exists() for k in range(per_task))
        rows[t] = {"attempted": ok + failed, "succeeded": ok, "failed": failed,
                   "success_rate": ok / (ok + failed) if ok + failed else None}
    attempted = sum(r["attempted"] for r in rows.values())
    succeeded = sum(r["succeeded"] for r in rows.values())
    return {"suite": suite, "per_task": rows, "attempted": attempted, "succeeded": succeeded,
            "failed": attempted - succeeded, "success_rate": succeeded / attempted if attempted else None}


def _print_summary(summary: dict) -> None:
    print(f"expert on {summary['suite']}: {summary['succeeded']}/{summary['attempted']} succeeded "
          f"({summary['failed']} failures, not kept)")
    for t, row in summary["per_task"].items():
        print(f"  task {t}: {row['succeeded']}/{row['attempted']}")
    if "recovery" in summary:
        rec = summary["recovery"]
        print(f"recovery demonstrations: {rec['succeeded']}/{rec['attempted']} succeeded")


def _load(path: Path) -> dict:
    with np.load(path, allow_pickle=False) as z:
        ep = {k: z[k] for k in z.files}
    ep["task_id"], ep["init_state"] = int(ep["task_id"]), int(ep["init_state"])
    ep["instruction"] = str(ep["instruction"])
    return ep


# --- worker side ---------------------------------------------------------------------------------------------
_ENVS: dict = {}


def _worker_init() -> None:
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C and terminates the pool


def _env(suite: str, task: int, env_cfg: dict):
    from vlactl.env.libero_env import EnvConfig, LiberoEnv

    key = (suite, task)
    if key not in _ENVS:
        for old in _ENVS.values():
            old.close()
        _ENVS.clear()  # one env per worker: envs hold a renderer and ~100 MB each
        _ENVS[key] = LiberoEnv(suite, task, EnvConfig(**env_cfg), render=True)
    return _ENVS[key]


def _generate_episode(job) -> bool:
    from vlactl.env.features import speeds
    from vlactl.expert.scripted import ExpertConfig, ScriptedExpert

    suite, task, k, recovery, seed, env_cfg, staging = job
    env = _env(suite, task, env_cfg)
    init_state = k % env.n_init_states
    # A recovery demonstration misses its first grasp on purpose and is recorded from the lift of that empty
    # gripper: the states a policy reaches after closing too high, and the way out (open, descend, grasp again).
    expert = ScriptedExpert(ExpertConfig(miss_first_grasp=recovery))
    start = time.time()
    obs = env.reset(init_state, seed=seed, render=True)
    expert.reset(env, obs)
    frames = {"image": [], "wrist_image": [], "libero_state": [], "robot_state": [], "action": []}
    positions = []
    success = False
    recording = not recovery
    for _ in range(env.max_steps):
        action = expert.act(obs)
        recording = recording or expert.phase == "lift"
        if recording:
            frames["image"].append(obs.images["image"])
            frames["wrist_image"].append(obs.images["wrist_image"])
            frames["libero_state"].append(obs.libero_state)
            frames["robot_state"].append(obs.state)
            frames["action"].append(action)
            positions.append(obs.state[:3])
        obs, success = env.step(action, render=True)
        if success:
            break
    positions.append(obs.state[:3])
    stem = _episode_stem(Path(staging), task, k, recovery)
    stem.parent.mkdir(parents=True, exist_ok=True)
    meta = {"task_id": task, "init_state": init_state, "seed": seed, "steps": len(frames["action"]),
            "wall_s": round(time.time() - start, 2)}
    if not success:
        atomic_write_json(stem.with_suffix(".json"), {**meta, "success": False, "expert_phase": expert.phase})
        return False
    arrays = {key: np.stack(v) for key, v in frames.items()}
    arrays["action"] = np.clip(arrays["action"], -1.0, 1.0).astype(np.float32)
    arrays["speed"] = speeds(np.stack(positions))[: len(arrays["action"])]
    with atomic_path(stem.with_suffix(".npz")) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays, task_id=task, init_state=init_state, instruction=env.instruction,
                     seed=seed, wall_s=meta["wall_s"])
    return True
