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


def user_image(frame: int, size: int, camera: str) -> np.ndarray:
    """A smooth image whose red level tells the dataset's frame `frame` apart (6 levels a frame): lossy video keeps
    both within a level or two."""
    ramp = np.arange(size) * 50 // size
    red = np.broadcast_to(6 * frame + ramp[None, :], (size, size))
    image = np.stack([red, np.broadcast_to(ramp[:, None] * 4, (size, size)), 255 - red], -1).astype(np.uint8)
    return image if camera == "image" else image[::-1].copy()


def write_user_dataset(root: Path, size: int = 256, video: bool = False, episodes: int = 4, frames: int = 6,
                       cameras=("image", "wrist_image"), state_dim: int = 8) -> Path:
    """A LIBERO dataset as a user has one: written by LeRobot's own LeRobotDataset.create with LeRobot's LIBERO key
    names and nothing vlactl adds, at 10 fps, the cameras stored as images or as video (LeRobot's default: AV1,
    encoded by LeRobot through pyav's bundled libsvtav1). Episode k has frames + k frames; see `user_image`."""
    import os

    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    camera = {"dtype": "video" if video else "image", "shape": (size, size, 3),
              "names": ["height", "width", "channels"]}
    features = {f"observation.images.{cam}": dict(camera) for cam in cameras}
    features["observation.state"] = {"dtype": "float32", "shape": (state_dim,), "names": None}
    features["action"] = {"dtype": "float32", "shape": (7,), "names": None}
    ds = LeRobotDataset.create("user/libero", 10, features, root=root, robot_type="panda", use_videos=video)
    rng = np.random.default_rng(0)
    index = 0
    for k in range(episodes):
        for _ in range(frames + k):
            ds.add_frame({
                **{f"observation.images.{cam}": user_image(index, size, cam) for cam in cameras},
                "observation.state": rng.normal(size=state_dim).astype(np.float32),
                "action": rng.uniform(-1, 1, 7).astype(np.float32),
                "task": INSTRUCTIONS[k % len(INSTRUCTIONS)],
            })
            index += 1
        ds.save_episode()
    ds.finalize()
    return Path(root)
