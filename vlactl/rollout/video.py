"""Episode videos: agent view and wrist camera side by side, H.264 mp4 at the control rate."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vlactl.env.features import CONTROL_DT
from vlactl.io import atomic_path


def write_video(path: Path, frames: list[dict]) -> None:
    """`frames` are observations' image dicts ({"image", "wrist_image"}, HxWx3 uint8), written atomically."""
    import imageio_ffmpeg

    tiles = [np.ascontiguousarray(np.concatenate([f["image"], f["wrist_image"]], axis=1)) for f in frames]
    height, width = tiles[0].shape[:2]
    with atomic_path(path) as tmp:
        # The temporary name has no .mp4 suffix, so name the container explicitly; yuv420p needs even sizes only.
        writer = imageio_ffmpeg.write_frames(
            str(tmp), (width, height), fps=round(1 / CONTROL_DT), output_params=["-f", "mp4"], macro_block_size=2
        )
        writer.send(None)
        for tile in tiles:
            writer.send(tile)
        writer.close()
