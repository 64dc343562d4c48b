"""The demonstration constants constraints are stated in (vlactl.data.motion), on a hand that lags its command."""

import numpy as np

from vlactl.data import frames, motion
from vlactl.data.lerobot_format import ACTION_KEY, STATE_KEY


def _lagging_hand(monkeypatch, gain=0.0125, episodes=6, steps=60):
    """Commands held for 15 steps at a time; the hand closes half its gap to gain x command each step."""
    rng = np.random.default_rng(0)
    states, actions, index = [], [], []
    for e in range(episodes):
        pos, vel = np.zeros(3), np.zeros(3)
        for t in range(steps):
            if t % 15 == 0:
                command = rng.uniform(-1, 1, 3)
            states.append(np.r_[pos, np.zeros(5)])
            actions.append(np.r_[command, np.zeros(4)])
            index.append(e)
            vel = vel + 0.5 * (gain * command - vel)
            pos = pos + vel
    cols = {STATE_KEY: np.array(states), ACTION_KEY: np.array(actions), "episode_index": np.array(index)}
    monkeypatch.setattr(frames, "read_columns", lambda root, keys: {k: cols[k] for k in keys})


def test_metres_per_unit_is_what_a_steady_command_moves_the_hand(monkeypatch, tmp_path):
    _lagging_hand(monkeypatch)
    assert abs(motion.metres_per_unit(tmp_path) - 0.0125) < 0.0125 * 0.02
    moved, command = motion._steps(tmp_path)  # the slope over every step, transients included, says less
    assert (moved * command).sum() / (command * command).sum() < 0.0125 * 0.95
