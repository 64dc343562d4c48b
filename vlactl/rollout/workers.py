"""Worker side of a rollout: each process loads the agent once, keeps one env (per task), runs batches of episodes.

Env creation costs seconds, so work comes in per-task batches; each finished episode is written as a part
(`vlactl.rollout.parts`) right away, so an interruption loses at most the episodes in flight.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from vlactl.env.perturbations import Perturbation
from vlactl.rollout import parts
from vlactl.rollout.agents import load_agent
from vlactl.rollout.constrained import ConstrainedAgent, Steering, reading_columns
from vlactl.rollout.constraints import as_constraints, constraint_name, filter_hook, judge_all, parse_constraints
from vlactl.rollout.episode import run_episode


@dataclass(frozen=True)
class RunSpec:
    """What every worker needs to know about the run (pickled once per worker)."""

    out: str
    suite: str
    model: str
    seed: int  # episode k runs with seed + k
    max_steps: int
    replan_every: int | None
    snap_gripper: bool
    video: bool
    env: dict
    load_policy: Callable | None = None  # None: the model registry; tests pass a fixture loader
    constraint: str = "none"  # one (`gripper=open`) or several (`height=high,speed=low`)
    window: int | None = None
    steering: Steering = Steering("none")
    start_gripper: str = "open"  # resolved: open or closed
    perturbation: Perturbation | None = None
    policy: str | None = None  # ws://HOST:PORT: the model runs in a `vlactl serve` process (vlactl.serve)
    episode_noise: bool = True  # each episode's sampling noise restarts from its own seed, not the model's one
    ensemble: float | None = None  # temporal ensembling's coefficient (VLAAgent); None: chunks as predicted


@dataclass(frozen=True)
class Batch:
    task: int
    episodes: tuple[int, ...]


_SPEC: RunSpec | None = None
_AGENT = None
_ENV: dict = {}


def init_worker(spec: RunSpec) -> None:
    import signal

    import torch

    global _SPEC
    _SPEC = spec
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C and terminates the pool
    torch.set_num_threads(1)  # the simulator needs the other core; 2 threads made small forwards ~80x slower


def _agent():
    global _AGENT
    if _AGENT is None:  # loaded on first use, not in the initializer: a failing initializer respawns forever
        constraint = parse_constraints(_SPEC.constraint, _SPEC.window)
        steered = bool(constraint) and _SPEC.steering.method not in ("none", "filter")
        if _SPEC.policy:
            from vlactl.serve.client import RemoteAgent
            from vlactl.serve.protocol import encode_steer

            steer = encode_steer(_SPEC.constraint, _SPEC.window, _SPEC.steering, _SPEC.replan_every,
                                 _SPEC.snap_gripper) if steered else None
            _AGENT = RemoteAgent(_SPEC.policy, _SPEC.replan_every, _SPEC.snap_gripper, steer)
            return _AGENT
        _AGENT = load_agent(_SPEC.model, _SPEC.replan_every, _SPEC.load_policy, _SPEC.snap_gripper, _SPEC.ensemble)
        if steered:
            _AGENT = ConstrainedAgent(
                _AGENT.vla, constraint, _SPEC.steering, _SPEC.replan_every, _SPEC.snap_gripper
            )
    return _AGENT


def _env(task: int, render: bool):
    from vlactl.env.libero_env import EnvConfig, LiberoEnv

    if task not in _ENV:
        for old in _ENV.values():
            old.close()
        _ENV.clear()  # one env per worker: each holds a simulator (and a renderer) of ~100 MB
        _ENV[task] = LiberoEnv(_SPEC.suite, task, EnvConfig(**_SPEC.env), render=render)
    return _ENV[task]


def run_batch(batch: Batch) -> None:
    """Run the batch's episodes (the parent passes only unfinished ones), each saved as a part when done."""
    spec, agent = _SPEC, _agent()
    render = agent.needs_images or spec.video
    env = _env(batch.task, render)
    out = Path(spec.out)
    constraint = parse_constraints(spec.constraint, spec.window)
    for k in batch.episodes:
        init_state, seed = k % env.n_init_states, spec.seed + k
        result = run_episode(env, agent, init_state, seed, spec.max_steps, render, keep_frames=spec.video,
                             hooks=episode_hooks(spec, constraint), start_gripper=spec.start_gripper,
                             noise_seed=seed if spec.episode_noise else None)
        row = {
            "suite": spec.suite, "task_id": batch.task, "episode": k, "instruction": env.instruction,
            "init_state": init_state, "seed": seed, "success": result.success, "steps": result.steps,
            "wall_s": round(result.wall_s, 3), "model": spec.model, "method": spec.steering.label,
            "constraint": constraint_name(constraint), "start_gripper": spec.start_gripper,
            "perturbation": spec.perturbation.name if spec.perturbation else "none",
        }
        steps = parts.steps_frame(batch.task, k, result)
        if constraint:
            threshold = spec.steering.bounds.speed_threshold
            steps = judge_part(constraint, row, steps, threshold, getattr(agent, "readings", {}))
        if spec.video:
            from vlactl.rollout.video import step_captions, write_video

            captions = step_captions(constraint_name(constraint), steps) if constraint and len(steps) else None
            write_video(out / "videos" / f"task{batch.task:02d}_ep{k:04d}.mp4", result.frames, captions)
        parts.write(out, row, steps)


def episode_hooks(spec: RunSpec, constraint) -> list:
    """Fresh per-episode step hooks: the safety filter (method=filter), then the perturbation, which overrides
    whatever acts while it is on."""
    hooks = []
    plan = spec.steering
    if plan.method == "filter":
        hooks.append(filter_hook(constraint, plan.bounds, plan.pause))
    if spec.perturbation is not None:
        hooks.append(spec.perturbation.hook())
    return hooks


def judge_part(constraint, row: dict, steps, speed_threshold: float, readings: dict):
    """An episode's step table judged against the constraint (its satisfaction goes into `row`; under several, each
    one's as well, `satisfaction_<feature>`), with the probe readings of the steered predictions (`readings`: step ->
    `reading_columns`; none without steering)."""
    constraints = as_constraints(constraint)
    steps, row["satisfaction"], own = judge_all(constraints, steps, float(steps["z"].iloc[0]), speed_threshold)
    if len(constraints) > 1:
        row.update({f"satisfaction_{feature}": value for feature, value in own.items()})
    for column in reading_columns(constraints):
        steps[column] = [readings.get(t, {}).get(column) for t in steps["t"]]
    return steps
