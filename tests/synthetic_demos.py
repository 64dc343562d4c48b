"""Synthetic inputs in the real formats: observations for models, a tiny LeRobot v3 demonstration dataset for training."""

from pathlib import Path

import numpy as np

def observation(batch: int = 2, seed: int = 0):
    """Random camera images and states; the second instruction has words no tokenizer here has seen."""
    from vlactl.models.base import PolicyInput

    rng = np.random.default_rng(seed)
    images = {cam: rng.integers(0, 256, (batch, 128, 128, 3), dtype=np.uint8) for cam in ("image", "wrist_image")}
    instructions = ["pick up the black bowl on the stove and place it on the plate", "an unseen instruction"]
    return PolicyInput(images, rng.normal(size=(batch, 8)).astype(np.float32), instructions[:batch])


INSTRUCTIONS = ["pick up the black bowl and place it on the plate", "open the top drawer"]


def write_synthetic_demos(root: Path, episodes: int = 3, frames: int = 12, seed: int = 0) -> Path:
    from vlactl.data.lerobot_format import write_dataset

    rng = np.random.default_rng(seed)

    def episode(k: int) -> dict:
        n = frames + k
        return {
            "image": rng.integers(0, 256, (n, 128, 128, 3), dtype=np.uint8),
            "wrist_image": rng.integers(0, 256, (n, 128, 128, 3), dtype=np.uint8),
            "libero_state": rng.normal(size=(n, 8)),
            "action": rng.uniform(-1, 1, (n, 7)).astype(np.float32),
            "robot_state": rng.normal(size=(n, 7)),
            "speed": rng.uniform(0, 0.2, n),
            "task_id": k % len(INSTRUCTIONS),
            "init_state": k,
            "instruction": INSTRUCTIONS[k % len(INSTRUCTIONS)],
        }

    write_dataset(Path(root), "vlactl/synthetic", 20, 128, (episode(k) for k in range(episodes)))
    return Path(root)
