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
    """One caption per policy step from a judged step table (vlactl.rollout.constraints.judge_all and the agent's
    reading columns). `constraint`: one (`height=high`) or several (`height=high,speed=low`: each constraint's part
    from its own `_<feature>` columns, side by side)."""
    import pandas as pd

    def number(row, key):
        value = row.get(key)
        return None if value is None or pd.isna(value) else float(value)

    names = constraint.split(",")
    suffixes = [""] if len(names) == 1 else [f"_{name.partition('=')[0]}" for name in names]
    lines = []
    for row in steps.to_dict("records"):
        heads, pushes = [], []
        for name, suffix in zip(names, suffixes):
            side = ">=" if name.endswith(("closed", "high")) else "<="
            inside = bool(row[f"in_window{suffix}"])
            value, level = number(row, f"constraint_value{suffix}"), number(row, f"constraint_level{suffix}")
            ok = inside and bool(row[f"satisfied{suffix}"])  # missing only outside the window
            heads.append(f"{name} " + ("in window" if inside else "after window") +
                         f"  {value - level:+.3f} {side} 0" + (" ok" if ok else ""))
            tag = f"{suffix[1:]} " if suffix else ""
            if number(row, f"action_before{suffix}") is not None:
                pushes.append(f"{tag}act {row[f'action_before{suffix}']:+.2f}->{row[f'action_after{suffix}']:+.2f} "
                              f"in [{row[f'bound_lo{suffix}']:+.2f}, {row[f'bound_hi{suffix}']:+.2f}]")
            elif number(row, f"reading_before{suffix}") is not None:
                pushes.append(f"{tag}probe {row[f'reading_before{suffix}']:+.2f}->{row[f'reading_after{suffix}']:+.2f}")
        lines.append(f"t={row['t']} " + " | ".join(heads) + ("\n" + " | ".join(pushes) if pushes else ""))
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
