"""What decides a demonstration's content: the kinds of episode, and the worker that records one (the expert in
its environment, under a kind's perturbation, saved atomically to the staging folder). `vlactl demos`
(vlactl/data/demos.py) schedules these and writes the dataset; a staging folder's code fingerprint hashes this module,
the expert and the environment, not that bookkeeping, so editing it does not orphan staged episodes."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vlactl.io import atomic_path, atomic_write_json


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


def episode_stem(staging: Path, task: int, k: int, kind: Kind = ORDINARY) -> Path:
    return staging / f"task{task:02d}" / f"{kind.prefix}{k:04d}"


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


_ENVS: dict = {}


def worker_init() -> None:
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


def generate_episode(job) -> bool:
    from vlactl.env.features import speeds
    from vlactl.env.perturbations import DEMONSTRATED, random_perturbation
    from vlactl.expert.scripted import CLOSE, ExpertConfig, ScriptedExpert

    suite, task, k, kind, seed, env_cfg, action_noise, tilt_size, staging, replay = job
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
               else random_perturbation(np.random.default_rng(seed), k, kinds, tilt_size).hook() if kinds else None)
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
    stem = episode_stem(Path(staging), task, k, kind)
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
