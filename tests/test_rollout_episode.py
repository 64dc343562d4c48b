"""The rollout's pure parts without the simulator: the episode loop, chunk re-planning, step hooks, tables."""

import numpy as np
import pandas as pd
import pytest
import torch

from fixture_policy import FixedChunkPolicy
from vlactl.env.libero_env import Observation
from vlactl.models.registry import tiny_policy
from vlactl.rollout import parts
from vlactl.rollout.agents import VLAAgent
from vlactl.rollout.episode import run_episode
from vlactl.rollout.runner import batches
from vlactl.rollout.summary import format_summary, summarise


class FakeEnv:
    """Moves the end effector by 1 cm per unit of dz; succeeds once it has risen `goal` metres."""

    instruction = "rise"

    def __init__(self, goal=0.1):
        self.goal, self.z = goal, 0.0

    def reset(self, init_state, seed=0, render=False, gripper="open"):
        self.z = 0.0
        return self._obs()

    def step(self, action, render=False):
        self.z += 0.01 * action[2]
        return self._obs(), self.z >= self.goal - 1e-9

    def _obs(self):
        state = np.array([0, 0, self.z, np.pi, 0, 0, 1.0])
        return Observation(state=state, libero_state=np.zeros(8), raw={})


def test_chunks_replan_every_and_stop_at_success():
    policy = FixedChunkPolicy()
    agent = VLAAgent(policy)
    result = run_episode(FakeEnv(goal=0.03), agent, init_state=0, seed=0, max_steps=50, render=False)
    assert result.success and result.steps == 10  # 0.3 cm a step
    assert policy.calls == 5  # 2 of each 4-action chunk executed
    assert result.states.shape == (11, 7) and result.actions.shape == (10, 7)


def test_step_limit_and_hooks_replace_actions():
    seen = []

    def close_gripper(t, obs, action):
        seen.append(t)
        return np.r_[action[:6], 2.0]

    result = run_episode(FakeEnv(goal=1.0), VLAAgent(FixedChunkPolicy()), 0, 0, max_steps=6, render=False,
                         hooks=[close_gripper])
    assert not result.success and result.steps == 6 and seen == list(range(6))
    assert np.all(result.actions[:, 6] == 1.0)  # the hook's action, clipped to [-1, 1], is what ran and is logged


def test_agent_executes_the_nearest_trained_gripper_command():
    policy = FixedChunkPolicy()
    policy.predict_action_chunk = lambda obs: torch.tensor([[0.0] * 6 + [g] for g in (0.04, -0.3, 0.6, -0.9)])[None]
    policy.gripper_levels = (-1.0, 0.0, 1.0)
    raw, snapped, whole = VLAAgent(policy, snap_gripper=False), VLAAgent(policy), VLAAgent(policy, replan_every=4)
    for agent in (raw, snapped, whole):
        agent.reset(FakeEnv(), None)
    obs = FakeEnv()._obs()
    assert [raw.act(obs)[6] for _ in range(2)] == pytest.approx([0.04, -0.3])
    assert [snapped.act(obs)[6] for _ in range(2)] == [0.0, 0.0]  # near "hold": hold, not a full-speed move
    assert [whole.act(obs)[6] for _ in range(4)] == [0.0, 0.0, 1.0, -1.0]


def test_embedded_models_declare_their_gripper_commands():
    assert tiny_policy("hybrid").gripper_levels == (-1.0, 0.0, 1.0)
    assert FixedChunkPolicy().gripper_levels is None  # other models: the command as predicted


def test_steps_table_and_summary():
    result = run_episode(FakeEnv(goal=0.03), VLAAgent(FixedChunkPolicy()), 0, 0, max_steps=50, render=False)
    steps = parts.steps_frame(3, 7, result)
    assert list(steps.columns) == parts.STEP_COLUMNS and len(steps) == 10
    assert np.allclose(steps["speed"], 0.003 / 0.05)
    assert steps[parts.OBJECT_COLUMNS].isna().all().all()  # an environment that tracks no object
    episodes = pd.DataFrame({"task_id": [0, 0, 1], "instruction": ["a", "a", "b"], "success": [True, False, True],
                             "steps": [10, 220, 30]})
    summary = summarise(episodes)
    assert summary["successes"] == 2 and summary["episodes"] == 3 and summary["mean_steps_success"] == 20
    assert summary["per_task"][0]["success_rate"] == 0.5 and summary["per_task"][1]["mean_steps"] == 30
    assert summary["success_ci95"] == pytest.approx((0.2077, 0.9385), abs=1e-4)  # Wilson, 2 of 3
    assert format_summary(summary).splitlines()[0] == "success 2/3 (67%, 95% CI 21–94%)"


def test_batches_keep_tasks_together_unless_workers_would_idle():
    todo = [(t, k) for t in range(3) for k in range(4)]
    assert [(b.task, b.episodes) for b in batches(todo, 2)] == [(t, (0, 1, 2, 3)) for t in range(3)]
    assert [b.episodes for b in batches([(0, 0), (0, 1), (0, 2)], 2)] == [(0,), (1, 2)]
    assert batches([], 2) == []
