"""Episode videos: agent view and wrist camera side by side, H.264 mp4 at the control rate; under a constraint, a
caption strip below them per step: the window, the constrained quantity against its bound, and the push (the
bounded action quantity or the probe reading, before and after)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vlactl.env.features import CONTROL_DT
from vlactl.io import atomic_path


CAPTION_HEIGHT = 40


def step_captions(constraint: str, steps) -> list[str]:
    """One caption per policy step from a judged step table (vlactl.rollout.constraints.judge_steps and the agent's
    reading columns)."""
    import pandas as pd

    def number(row, key):
        value = row.get(key)
        return None if value is None or pd.isna(value) else float(value)

    lines = []
    for row in steps.to_dict("records"):
        side = ">=" if constraint.endswith(("closed", "high")) else "<="
        head = f"t={row['t']} {constraint} " + ("in window" if row["in_window"] else "after window")
        value, level = number(row, "constraint_value"), number(row, "constraint_level")
        judged = f"{value - level:+.3f} {side} 0" + (" ok" if row["in_window"] and row["satisfied"] else "")
        push = ""
        if number(row, "action_before") is not None:
            push = (f"\nact {row['action_before']:+.2f}->{row['action_after']:+.2f} "
                    f"in [{row['bound_lo']:+.2f}, {row['bound_hi']:+.2f}]")
        elif number(row, "reading_before") is not None:
            push = f"\nprobe {row['reading_before']:+.2f}->{row['reading_after']:+.2f}"
        lines.append(f"{head}  {judged}{push}")
    return lines


def _captioned(tile: np.ndarray, text: str) -> np.ndarray:
    from PIL import Image, ImageDraw

    strip = Image.new("RGB", (tile.shape[1], CAPTION_HEIGHT), (20, 20, 20))
    ImageDraw.Draw(strip).multiline_text((3, 2), text, fill=(235, 235, 235), spacing=2)
    return np.concatenate([tile, np.asarray(strip)], axis=0)


def write_video(path: Path, frames: list[dict], captions: list[str] | None = None) -> None:
    """`frames` are observations' image dicts ({"image", "wrist_image"}, HxWx3 uint8), written atomically; with
    `captions` (one per action), frame t carries the caption of the step taken from it."""
    import imageio_ffmpeg

    tiles = [np.ascontiguousarray(np.concatenate([f["image"], f["wrist_image"]], axis=1)) for f in frames]
    if captions is not None:
        tiles = [_captioned(tile, captions[min(t, len(captions) - 1)]) for t, tile in enumerate(tiles)]
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
