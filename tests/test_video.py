"""Constrained episodes' videos carry a caption per step: the window, the quantity against its bound, the push."""

import numpy as np
import pandas as pd

from vlactl.rollout.video import CAPTION_HEIGHT, step_captions, write_video


def test_captions_name_the_window_the_bound_and_the_push(tmp_path):
    steps = pd.DataFrame({
        "t": [0, 1, 2], "in_window": [True, True, False], "constraint_value": [1.0, 1.02, 0.9],
        "constraint_level": [1.0, 1.0, 1.0], "satisfied": pd.array([True, True, pd.NA], dtype="boolean"),
        "action_before": [-0.4, None, None], "action_after": [-0.01, None, None],
        "bound_lo": [0.0, None, None], "bound_hi": [np.inf, None, None],
        "reading_before": [None, None, None], "reading_after": [None, None, None],
    })
    captions = step_captions("height=high", steps)
    assert captions[0].startswith("t=0 height=high in window  +0.000 >= 0 ok")
    assert "act -0.40->-0.01 in [+0.00, +inf]" in captions[0] and "act" not in captions[1]
    assert "after window  -0.100 >= 0" in captions[2] and "ok" not in captions[2]

    import imageio_ffmpeg

    frames = [{"image": np.zeros((32, 32, 3), np.uint8), "wrist_image": np.zeros((32, 32, 3), np.uint8)}] * 4
    write_video(tmp_path / "v.mp4", frames, captions)
    reader = imageio_ffmpeg.read_frames(str(tmp_path / "v.mp4"))
    meta = next(reader)
    assert tuple(meta["size"]) == (64, 32 + CAPTION_HEIGHT)
    assert sum(1 for _ in reader) == 4
