"""The demonstration dataset's LeRobot v3 schema (docs/formats.md) and a writer from finished episodes."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np

from vlactl.env.features import ACTION_FEATURES, STATE_FEATURES

# LeRobot's LIBERO key names, so a user's own LIBERO dataset in LeRobot format reads the same way.
IMAGE_KEY, WRIST_KEY = "observation.images.image", "observation.images.wrist_image"
STATE_KEY, ACTION_KEY, ROBOT_STATE_KEY = "observation.state", "action", "observation.robot_state"
STATE_DIM, ACTION_DIM = 8, 7  # LIBERO's state (openpi/LeRobot convention) and action


WRITER_THREADS = 2


def features(image_size: int) -> dict:
    img = {"dtype": "image", "shape": (image_size, image_size, 3), "names": ["height", "width", "channels"]}
    return {
        IMAGE_KEY: img,
        WRIST_KEY: dict(img),
        STATE_KEY: {"dtype": "float32", "shape": (STATE_DIM,),
                    "names": ["x", "y", "z", "ax", "ay", "az", "q_left", "q_right"]},
        ACTION_KEY: {"dtype": "float32", "shape": (ACTION_DIM,), "names": list(ACTION_FEATURES)},
        ROBOT_STATE_KEY: {"dtype": "float32", "shape": (7,), "names": list(STATE_FEATURES)},
        "speed": {"dtype": "float32", "shape": (1,), "names": ["speed"]},
        "task_id": {"dtype": "int64", "shape": (1,), "names": None},
        "init_state": {"dtype": "int64", "shape": (1,), "names": None},
    }


def write_dataset(root: Path, repo_id: str, fps: int, image_size: int, episodes, progress=None) -> None:
    """Write `episodes` (iterable of dicts of per-frame arrays, see vlactl.data.demos) as a LeRobot v3 dataset.

    Built in a sibling folder and renamed into place at the end, so `root` is never a half-written dataset.
    """
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    root = Path(root)
    building = root.with_name(root.name + ".building")
    shutil.rmtree(building, ignore_errors=True)
    # PNG encoding in writer threads overlaps the parquet work of the main thread: 8.6 s against 11.5 s for 3 episodes
    # beside a 2-worker demo generation on 2 cores (more threads than cores gains nothing)
    ds = LeRobotDataset.create(repo_id, fps, features(image_size), root=building, robot_type="panda", use_videos=False,
                               image_writer_threads=WRITER_THREADS)
    for ep in episodes:
        n = len(ep["action"])
        for t in range(n):
            ds.add_frame({
                IMAGE_KEY: ep["image"][t],
                WRIST_KEY: ep["wrist_image"][t],
                STATE_KEY: ep["libero_state"][t].astype(np.float32),
                ACTION_KEY: ep["action"][t].astype(np.float32),
                ROBOT_STATE_KEY: ep["robot_state"][t].astype(np.float32),
                "speed": np.float32([ep["speed"][t]]),
                "task_id": np.int64([ep["task_id"]]),
                "init_state": np.int64([ep["init_state"]]),
                "task": str(ep["instruction"]),
            })
        ds.save_episode()
        if progress is not None:
            progress.update(1)
    ds.finalize()
    ds.stop_image_writer()
    if root.exists():
        shutil.rmtree(root)
    os.replace(building, root)
