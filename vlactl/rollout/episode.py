"""One closed-loop episode: reset to a fixed init state, act until LIBERO's success check or the step limit.

The loop knows nothing about the model (an agent acts) or about constraints: a *step hook*
`hook(t, obs, action) -> action` sees every step before the action is applied and may replace the action. That is
where per-step interventions and their bookkeeping attach (constraint windows, control on/off), without touching
the loop.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

StepHook = Callable[[int, object, np.ndarray], np.ndarray]


@dataclass
class EpisodeResult:
    success: bool
    states: np.ndarray  # (steps + 1, 7) SPEC.md §2 state before each action, and after the last one
    actions: np.ndarray  # (steps, 7) the actions applied, clipped to LIBERO's [-1, 1]
    wall_s: float
    object_positions: np.ndarray  # (steps + 1, 3) the task's object (Observation.object_pos), as states
    frames: list[dict] = field(default_factory=list)  # camera images per observation, only when kept

    @property
    def steps(self) -> int:
        return len(self.actions)


def run_episode(
    env,
    agent,
    init_state: int,
    seed: int,
    max_steps: int,
    render: bool,
    keep_frames: bool = False,
    hooks: Sequence[StepHook] = (),
    start_gripper: str = "open",
    noise_seed: int | None = None,
) -> EpisodeResult:
    """`noise_seed`: where the agent's sampling noise restarts (`VLA.reset`); None: the model's own seed."""
    start = time.perf_counter()
    obs = env.reset(init_state, seed=seed, render=render, gripper=start_gripper)
    agent.reset(env, obs, noise_seed)
    states, objects, actions, frames = [obs.state], [obs.object_pos], [], [obs.images] if keep_frames else []
    success = False
    for t in range(max_steps):
        action = np.asarray(agent.act(obs), dtype=np.float64)
        for hook in hooks:
            action = hook(t, obs, action)
        action = np.clip(action, -1.0, 1.0)  # log what the controller really receives
        obs, success = env.step(action, render=render)
        actions.append(action)
        states.append(obs.state)
        objects.append(obs.object_pos)
        if keep_frames:
            frames.append(obs.images)
        if success:
            break
    return EpisodeResult(
        success=success,
        states=np.stack(states),
        actions=np.stack(actions) if actions else np.zeros((0, 7)),
        wall_s=time.perf_counter() - start,
        object_positions=np.stack(objects),
        frames=frames,
    )
