"""`vlactl demos`: scripted-expert demonstrations, generated in worker processes, written as a LeRobot dataset.

Two phases, so an interruption never leaves a half-written episode and a re-run resumes where it stopped:
1. each episode runs in a worker and is saved atomically to `<output_dir>.staging/` (successes as .npz, failures
   as a small .json), skipped on re-run if already there;
2. the LeRobot v3 dataset is built from the staged successes into a sibling folder and renamed into place.

A staging folder records what made its episodes (a hash of the expert, environment and recording sources and of the
`env` settings, not of this scheduling and writing code) and refuses new episodes made otherwise: a resumed run must not mix expert versions or render settings
in one dataset.
"""

from __future__ import annotations

import hashlib
import json
import multiprocessing as mp
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from vlactl.config import resolve_path, save_config
from vlactl.data import recording
from vlactl.data.recording import KINDS, ORDINARY, REPLAYED, Kind, Replay, episode_stem, generate_episode, worker_init
from vlactl.env.perturbations import parse_tilt_size
from vlactl.errors import UsageError, check_choice, check_non_negative, check_positive
from vlactl.io import atomic_write_json, ensure_writable_dir

SUMMARY_NAME = "vlactl_demos.json"
CODE_NAME = "code.json"  # in the staging folder: the code fingerprint its episodes were made with
REPLAY_STRIDE = 1000  # the r-th replayed run's episodes are numbered from r * REPLAY_STRIDE


def _done(staging: Path, task: int, k: int, kind: Kind) -> bool:
    stem = episode_stem(staging, task, k, kind)
    return stem.with_suffix(".npz").exists() or stem.with_suffix(".json").exists()


def recorder_sources() -> list[Path]:
    """The sources that decide an episode's content: the expert, the environment and the recording worker."""
    package = Path(__file__).resolve().parents[1]
    return sorted([*(package / "expert").glob("*.py"), *(package / "env").glob("*.py"), Path(recording.__file__)])


def code_fingerprint(env_cfg: dict) -> str:
    """Hash of the recorder's sources and the environment settings (image size, shadows, ...: they change the
    pixels)."""
    h = hashlib.sha256()
    for path in recorder_sources():
        h.update(path.name.encode() + path.read_bytes())
    h.update(json.dumps(env_cfg, sort_keys=True).encode())
    return h.hexdigest()[:16]


def staged_code(staging: Path, env_cfg: dict, adding: bool, replay: list | None = None) -> str:
    """The fingerprint (code_fingerprint) of the staging folder's episodes, recorded on first use. Adding episodes
    made by other code or settings is refused (a dataset of 2026-11-29 mixed expert versions this way,
    docs/models.md). Replayed episodes also depend on the runs they replay (`replay`: [folder, replay_first] per run,
    in order), recorded beside it: replays of other runs are refused, more runs after the recorded ones are not, and
    the other kinds, which do not depend on them, may come from a set whose staging this one extends."""
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
    if before and isinstance(before[0], str):  # recorded before several runs could be replayed: one [folder, first]
        before = [before]
    if adding and replay and before and replay[:len(before)] != before[:len(replay)] \
            and any(staging.glob(f"task*/{REPLAYED.prefix}*")):
        raise UsageError(f"{staging} holds episodes replayed from {_runs(before)}, not from {_runs(replay)}: choose "
                         "another output_dir=... or delete that folder")
    record = {"code": staged}
    now = before
    if adding and replay and not (before and before[:len(replay)] == replay):  # not the recorded runs' first ones
        now = replay  # more runs after the recorded ones, or other runs where none were replayed yet
    if now:
        record["replay"] = now
    if staged is not None and record != saved:
        atomic_write_json(mark, record)
    return staged or "unknown"


def _runs(replay: list) -> str:
    return ", ".join(f"{folder} (replay_first={first})" for folder, first in replay)


def run_demos(cfg: DictConfig) -> dict:
    from vlactl.env.libero_env import check_env_config
    from vlactl.env.suites import SUITES, resolve_tasks

    check_choice("suite", cfg.suite, SUITES)
    for kind in KINDS:
        check_non_negative(kind.count, cfg[kind.count])
    check_non_negative("action_noise", cfg.action_noise)
    tilt = parse_tilt_size(cfg.tilt_size)
    check_positive("workers", cfg.workers)
    env_cfg = OmegaConf.to_container(cfg.env, resolve=True)
    check_env_config(env_cfg)
    tasks = resolve_tasks(cfg.suite, cfg.tasks)
    out = resolve_path(cfg.output_dir)
    ensure_writable_dir(out.parent, requested=out)
    staging = ensure_writable_dir(out.with_name(out.name + ".staging"))
    save_config(cfg, staging)

    runs = replay_runs(cfg.replay_from)
    replays = load_replays(runs, cfg.suite, tasks, cfg.replay_first, cfg[REPLAYED.count])
    keys = {kind: range(cfg[kind.count]) for kind in KINDS}
    keys[REPLAYED] = [k for t, k in replays if t == tasks[0]]
    everything = [(t, k, kind, replays[t, k].seed if kind == REPLAYED else cfg.seed + kind.seed_offset + k)
                  for kind in KINDS for t in tasks for k in keys[kind]]
    noise = float(cfg.action_noise)
    work = [(cfg.suite, t, k, kind, seed, env_cfg, noise, tilt, str(staging),
             replays[t, k] if kind == REPLAYED else None)
            for t, k, kind, seed in everything if not _done(staging, t, k, kind)]
    # The noise scale, the tilts (and the replayed run) decide episodes' content: a resumed run with others must not
    # mix them.
    replay = [[str(resolve_path(run)), int(cfg.replay_first)] for run in runs] if replays else None
    settings = {**env_cfg, "action_noise": noise, "tilt_size": list(tilt)}
    code = staged_code(staging, settings, adding=bool(work), replay=replay)
    total = len(everything)
    bar = tqdm(total=total, initial=total - len(work), desc=f"demos {cfg.suite}", unit="ep")
    if work:
        ctx = mp.get_context("spawn")
        with ctx.Pool(min(cfg.workers, len(work)), initializer=worker_init) as pool:
            for ok in pool.imap_unordered(generate_episode, work):
                bar.update(1)
                bar.set_postfix_str("ok" if ok else "expert failed")
    bar.close()

    summary = summarise(staging, cfg.suite, tasks, keys[ORDINARY])
    for kind in KINDS[1:]:
        if keys[kind]:
            summary[kind.summary_key] = summarise(staging, cfg.suite, tasks, keys[kind], kind)
    episodes = sorted(
        stem.with_suffix(".npz")
        for t, k, kind, _ in everything
        if (stem := episode_stem(staging, t, k, kind)).with_suffix(".npz").exists()
    )
    from vlactl.data.lerobot_format import write_dataset

    record = {"config": OmegaConf.to_container(cfg), "code": code, **summary}
    written = out / "meta" / SUMMARY_NAME
    # The summary is written last, after the dataset is renamed into place: an equal one means these episodes are
    # already there, and a resumed queue skips minutes of writing.
    if written.is_file() and json.loads(written.read_text()) == json.loads(json.dumps(record, default=str)):
        print(f"{out}: already holds these {len(episodes)} episodes, not written again")
    else:
        with tqdm(total=len(episodes), desc="writing LeRobot dataset", unit="ep") as wbar:
            write_dataset(out, f"vlactl/{cfg.suite}", cfg.fps, cfg.env.image_size, (_load(p) for p in episodes), wbar)
        atomic_write_json(written, record)
    save_config(cfg, out)
    _print_summary(summary)
    return summary


def replay_runs(replay_from) -> list[str]:
    """`replay_from` as a list of run folders: one run, a list of them, or none."""
    if replay_from is None:
        return []
    return [replay_from] if isinstance(replay_from, str) else [str(run) for run in replay_from]


def load_replays(runs: list[str], suite: str, tasks: list[int], first: int, count: int) -> dict:
    """(task, k) -> Replay of the j-th episode numbered `first` or later of that task in the r-th run,
    k = r * REPLAY_STRIDE + j: finished `vlactl rollout` runs' episodes (usually cut at their window, `max_steps=15`),
    each replayed from the same initial state, seed and gripper, so that the expert records its way back from exactly
    the states that run's policy and steering reached (DAgger-style); `count` from each run. `first` skips the
    episodes whose initial states an evaluation starts from (a 10 x 10 run: 0-9)."""
    if not count:
        return {}
    if not runs:
        raise UsageError("replayed_episodes_per_task needs replay_from=<a vlactl rollout run folder, or a list of them>")
    check_non_negative("replay_first", first)
    if count > REPLAY_STRIDE:
        raise UsageError(f"replayed_episodes_per_task={count}: at most {REPLAY_STRIDE} from each run")
    replays = {}
    for r, run in enumerate(runs):
        replays |= {(t, r * REPLAY_STRIDE + j): replay for (t, j), replay in
                    _run_replays(run, suite, tasks, first, count).items()}
    return replays


def _run_replays(run: str, suite: str, tasks: list[int], first: int, count: int) -> dict:
    """(task, j) -> Replay of the run's j-th episode of that task numbered `first` or later (a run started at
    `first_episode=15` gives its episodes 15.. for replay_first=10)."""
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
        numbers = sorted(e for task, e in episodes.index if task == t and e >= first)
        if len(numbers) < count:
            raise UsageError(f"replay_from={run} has {len(numbers)} episodes of task {t} numbered {first} or later "
                             f"(replay_first); replayed_episodes_per_task={count} needs {count}")
        for k, number in enumerate(numbers[:count]):
            key = (t, number)
            row = episodes.loc[key]
            actions = steps.get_group(key).sort_values("t")[list(ACTION_FEATURES)].to_numpy(np.float64)
            replays[t, k] = Replay(int(row["init_state"]), int(row["seed"]), str(row["start_gripper"]), actions)
    return replays


def summarise(staging: Path, suite: str, tasks: list[int], keys, kind: Kind = ORDINARY) -> dict:
    rows = {}
    for t in tasks:
        ok = sum(episode_stem(staging, t, k, kind).with_suffix(".npz").exists() for k in keys)
        failed = sum(episode_stem(staging, t, k, kind).with_suffix(".json").exists() for k in keys)
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


