"""`vlactl demos`: scripted-expert demonstrations, generated in worker processes, written as a LeRobot dataset.

Two phases, so an interruption never leaves a half-written episode and a re-run resumes where it stopped:
1. each episode runs in a worker and is saved atomically to `<output_dir>.staging/` (successes as .npz, failures
   as a small .json), skipped on re-run if already there;
2. the LeRobot v3 dataset is built from the staged successes into a sibling folder and renamed into place.

A staging folder records what made its episodes (a hash of the expert, environment and recording sources and of the
`env` settings) and refuses new episodes made otherwise: a resumed run must not mix expert versions or render settings
in one dataset.
"""

from __future__ import annotations

import hashlib
import json
import multiprocessing as mp
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from vlactl.config import resolve_path, save_config
from vlactl.errors import UsageError, check_choice, check_non_negative, check_positive
from vlactl.io import atomic_path, atomic_write_json, ensure_writable_dir

SUMMARY_NAME = "vlactl_demos.json"
CODE_NAME = "code.json"  # in the staging folder: the code fingerprint its episodes were made with


@dataclass(frozen=True)
class Kind:
    """A kind of demonstration: its count option, the prefix of its staged files, where its seeds start (apart from
    the other kinds'), and the summary key it is reported under."""

    count: str
    prefix: str
    seed_offset: int
    summary_key: str


ORDINARY = Kind("episodes_per_task", "ep", 0, "")
RECOVERY = Kind("recovery_episodes_per_task", "rec", 100_000, "recovery")
CLOSED_START = Kind("closed_start_episodes_per_task", "cls", 200_000, "closed_start")
CLOSED_APPROACH = Kind("closed_approach_episodes_per_task", "cla", 300_000, "closed_approach")
NOISY = Kind("noisy_episodes_per_task", "noi", 400_000, "noisy")
PERTURBED = Kind("perturbed_episodes_per_task", "per", 500_000, "perturbed")
TILTED = Kind("tilted_episodes_per_task", "tlt", 600_000, "tilted")
REPLAYED = Kind("replayed_episodes_per_task", "rpl", 700_000, "replayed")  # seeds: the replayed run's own
KINDS = (ORDINARY, RECOVERY, CLOSED_START, CLOSED_APPROACH, NOISY, PERTURBED, TILTED, REPLAYED)
CLOSED_STEPS = (5, 20)  # closed-start episodes hold the gripper closed this many steps (drawn per episode)


def _episode_stem(staging: Path, task: int, k: int, kind: Kind = ORDINARY) -> Path:
    return staging / f"task{task:02d}" / f"{kind.prefix}{k:04d}"


def _done(staging: Path, task: int, k: int, kind: Kind) -> bool:
    stem = _episode_stem(staging, task, k, kind)
    return stem.with_suffix(".npz").exists() or stem.with_suffix(".json").exists()


def code_fingerprint(env_cfg: dict) -> str:
    """Hash of what decides an episode's content: the sources of the expert, the environment and this recorder, and
    the environment settings (image size, shadows, ...: they change the pixels)."""
    package = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for path in sorted([*(package / "expert").glob("*.py"), *(package / "env").glob("*.py"), Path(__file__).resolve()]):
        h.update(path.name.encode() + path.read_bytes())
    h.update(json.dumps(env_cfg, sort_keys=True).encode())
    return h.hexdigest()[:16]


def staged_code(staging: Path, env_cfg: dict, adding: bool, replay: list | None = None) -> str:
    """The fingerprint (code_fingerprint) of the staging folder's episodes, recorded on first use. Adding episodes
    made by other code or settings is refused (a dataset of 2026-11-29 mixed expert versions this way,
    docs/models.md). Replayed episodes also depend on the run they replay (`replay`: its folder and replay_first),
    recorded beside it: replays of another run are refused, while the other kinds, which do not depend on it, may come
    from a set whose staging this one extends."""
    mark = staging / CODE_NAME
    current = code_fingerprint(env_cfg)
    saved = json.loads(mark.read_text()) if mark.exists() else {}
    staged = saved.get("code")
    if staged is None and not any(staging.glob("task*/*")):
        staged = current
    if adding and staged != current:
        made_by = f"code {staged}" if staged else "code of unknown version"
        raise UsageError(f"{staging} holds episodes made by {made_by}, not by this code and env settings ({current}); "
                         "new episodes would mix the two in one dataset: choose another output_dir=... or delete that "
                         "folder")
    before = saved.get("replay")
    if adding and replay is not None and before not in (None, replay) \
            and any(staging.glob(f"task*/{REPLAYED.prefix}*")):
        raise UsageError(f"{staging} holds episodes replayed from {before[0]} (replay_first={before[1]}), not from "
                         f"{replay[0]} (replay_first={replay[1]}): choose another output_dir=... or delete that folder")
    record = {"code": staged}
    if (now := replay if adding and replay is not None else before) is not None:  # only new replays change it
        record["replay"] = now
    if staged is not None and record != saved:
        atomic_write_json(mark, record)
    return staged or "unknown"


def run_demos(cfg: DictConfig) -> dict:
    from vlactl.env.libero_env import check_env_config
    from vlactl.env.suites import SUITES, resolve_tasks

    check_choice("suite", cfg.suite, SUITES)
    for kind in KINDS:
        check_non_negative(kind.count, cfg[kind.count])
    check_non_negative("action_noise", cfg.action_noise)
    check_positive("workers", cfg.workers)
    env_cfg = OmegaConf.to_container(cfg.env, resolve=True)
    check_env_config(env_cfg)
    tasks = resolve_tasks(cfg.suite, cfg.tasks)
    out = resolve_path(cfg.output_dir)
    ensure_writable_dir(out.parent, requested=out)
    staging = ensure_writable_dir(out.with_name(out.name + ".staging"))
    save_config(cfg, staging)

    replays = load_replays(cfg.replay_from, cfg.suite, tasks, cfg.replay_first, cfg[REPLAYED.count])
    everything = [(t, k, kind, replays[t, k].seed if kind == REPLAYED else cfg.seed + kind.seed_offset + k)
                  for kind in KINDS for t in tasks for k in range(cfg[kind.count])]
    noise = float(cfg.action_noise)
    work = [(cfg.suite, t, k, kind, seed, env_cfg, noise, str(staging),
             replays[t, k] if kind == REPLAYED else None)
            for t, k, kind, seed in everything if not _done(staging, t, k, kind)]
    # The noise scale (and the replayed run) decide episodes' content: a resumed run with others must not mix them.
    replay = [str(resolve_path(cfg.replay_from)), int(cfg.replay_first)] if replays else None
    code = staged_code(staging, {**env_cfg, "action_noise": noise}, adding=bool(work), replay=replay)
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
    for kind in KINDS[1:]:
        if cfg[kind.count]:
            summary[kind.summary_key] = summarise(staging, cfg.suite, tasks, cfg[kind.count], kind)
    episodes = sorted(
        stem.with_suffix(".npz")
        for t, k, kind, _ in everything
        if (stem := _episode_stem(staging, t, k, kind)).with_suffix(".npz").exists()
    )
    from vlactl.data.lerobot_format import write_dataset

    with tqdm(total=len(episodes), desc="writing LeRobot dataset", unit="ep") as wbar:
        write_dataset(out, f"vlactl/{cfg.suite}", cfg.fps, cfg.env.image_size, (_load(p) for p in episodes), wbar)
    atomic_write_json(out / "meta" / SUMMARY_NAME, {"config": OmegaConf.to_container(cfg), "code": code, **summary})
    save_config(cfg, out)
    _print_summary(summary)
    return summary


@dataclass(frozen=True)
class Replay:
    """The start and executed actions of one episode of a rollout run, to be replayed before the expert takes over."""

    init_state: int
    seed: int
    start_gripper: str
    actions: np.ndarray  # (steps, 7)

    def hook(self, t: int, obs, executed: np.ndarray) -> np.ndarray:
        """The run's action at step t while it lasts, then the expert's."""
        return self.actions[t] if t < len(self.actions) else executed


def load_replays(run: str | None, suite: str, tasks: list[int], first: int, count: int) -> dict:
    """(task, k) -> Replay of the run's episode `first + k` of that task: a finished `vlactl rollout` run's episodes
    (usually cut at its window, `max_steps=15`), replayed from the same initial state, seed and gripper, so that the
    expert records its way back from exactly the states that run's policy and steering reached (DAgger-style).
    `first` skips the episodes whose initial states an evaluation starts from (a 10 x 10 run: 0-9)."""
    if not count:
        return {}
    if run is None:
        raise UsageError("replayed_episodes_per_task needs replay_from=<a vlactl rollout run folder>")
    check_non_negative("replay_first", first)
    folder = resolve_path(run)
    if not (folder / "episodes.parquet").exists():
        raise UsageError(f"replay_from={run}: no episodes.parquet there; give a finished `vlactl rollout` run folder")
    import pandas as pd

    episodes = pd.read_parquet(folder / "episodes.parquet").set_index(["task_id", "episode"])
    steps = pd.read_parquet(folder / "steps.parquet").groupby(["task_id", "episode"])
    if set(episodes["suite"]) != {suite}:
        raise UsageError(f"replay_from={run} ran suite {sorted(set(episodes['suite']))}, not suite={suite}")
    from vlactl.env.features import ACTION_FEATURES

    replays = {}
    for t in tasks:
        for k in range(count):
            key = (t, first + k)
            if key not in episodes.index:
                have = int((episodes.index.get_level_values(0) == t).sum())
                raise UsageError(f"replay_from={run} has {have} episodes of task {t}; replay_first={first} + "
                                 f"replayed_episodes_per_task={count} needs {first + count}")
            row = episodes.loc[key]
            actions = steps.get_group(key).sort_values("t")[list(ACTION_FEATURES)].to_numpy(np.float64)
            replays[t, k] = Replay(int(row["init_state"]), int(row["seed"]), str(row["start_gripper"]), actions)
    return replays


def summarise(staging: Path, suite: str, tasks: list[int], per_task: int, kind: Kind = ORDINARY) -> dict:
    rows = {}
    for t in tasks:
        ok = sum(_episode_stem(staging, t, k, kind).with_suffix(".npz").exists() for k in range(per_task))
        failed = sum(_episode_stem(staging, t, k, kind).with_suffix(".json").exists() for k in range(per_task))
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
    for kind in KINDS[1:]:
        if kind.summary_key in summary:
            part = summary[kind.summary_key]
            print(f"{kind.summary_key.replace('_', '-')} demonstrations: {part['succeeded']}/{part['attempted']} "
                  f"succeeded")


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
    from vlactl.env.perturbations import DEMONSTRATED, random_perturbation
    from vlactl.expert.scripted import CLOSE, ExpertConfig, ScriptedExpert

    suite, task, k, kind, seed, env_cfg, action_noise, staging, replay = job
    env = _env(suite, task, env_cfg)
    init_state = replay.init_state if replay else k % env.n_init_states
    # A recovery demonstration misses its first grasp on purpose and is recorded from the lift of that empty
    # gripper: the states a policy reaches after closing too high, and the way out (open, descend, grasp again).
    recovery = kind == RECOVERY
    # A closed-approach demonstration starts closed and the expert keeps it closed, label and all, until it is over
    # the grasp point, then opens and grasps: a closed gripper on the way is then a state the policy knows how to go
    # on from, which a gripper=closed constraint needs (docs/models.md). Contradicts closed-start labels: use one.
    closed_approach = kind == CLOSED_APPROACH
    expert = ScriptedExpert(ExpertConfig(miss_first_grasp=recovery, closed_approach=closed_approach))
    # A closed-start demonstration starts with the gripper closed and keeps it closed for its first few steps
    # whatever the expert says, while the recorded actions stay the expert's own (open): DART-style, the states
    # come from a perturbed execution and the labels from the expert, so a policy learns to open a gripper that
    # something else (a controller, a favourable start) closed.
    closed_steps = 0
    if kind == CLOSED_START:
        closed_steps = int(np.random.default_rng(seed).integers(*CLOSED_STEPS, endpoint=True))
    # A noisy demonstration executes the expert's translation commands plus Gaussian noise while recording the
    # expert's own commands (DART): the states spread around the expert's path, each labelled with the way back.
    noise_rng = np.random.default_rng(seed) if kind == NOISY else None
    # A perturbed demonstration hands the arm to a perturbation (raised, held, shifted, slowed, gripper closed) for a
    # stretch of steps, then back to the expert, recording the expert's own commands throughout: the way back from
    # the states a constraint or a push leaves a policy in (vlactl/env/perturbations.py).
    # A tilted one turns the hand a few degrees about world x and holds it there first: the residual turn a pushed
    # stop leaves a policy with (docs/steering.md).
    # A replayed one executes what a rollout run's policy did (under a steered constraint, say) from the same start,
    # then hands the arm to the expert: the way back from the states that policy and push really reach (DAgger).
    kinds = {PERTURBED: DEMONSTRATED, TILTED: ("tilt",)}.get(kind)
    perturb = (replay.hook if replay
               else random_perturbation(np.random.default_rng(seed), k, kinds).hook() if kinds else None)
    start = time.time()
    gripper = replay.start_gripper if replay else "closed" if closed_steps or closed_approach else "open"
    obs = env.reset(init_state, seed=seed, render=True, gripper=gripper)
    expert.reset(env, obs)
    frames = {"image": [], "wrist_image": [], "libero_state": [], "robot_state": [], "action": []}
    positions = []
    success = False
    recording = not recovery
    for t in range(env.max_steps):
        action = expert.act(obs)
        executed = np.concatenate([action[:-1], [CLOSE]]) if t < closed_steps else action
        if noise_rng is not None:
            executed = executed.copy()
            executed[:3] = np.clip(executed[:3] + noise_rng.normal(0.0, action_noise, 3), -1.0, 1.0)
        if perturb is not None:
            executed = perturb(t, obs, executed)
        recording = recording or expert.phase == "lift"
        if recording:
            frames["image"].append(obs.images["image"])
            frames["wrist_image"].append(obs.images["wrist_image"])
            frames["libero_state"].append(obs.libero_state)
            frames["robot_state"].append(obs.state)
            frames["action"].append(action)
            positions.append(obs.state[:3])
        obs, success = env.step(executed, render=True)
        if success:
            break
    positions.append(obs.state[:3])
    stem = _episode_stem(Path(staging), task, k, kind)
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
