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


def test_captions_of_two_constraints_name_each_with_its_own_window_and_push():
    steps = pd.DataFrame({
        "t": [0, 1], "in_window": [True, True], "satisfied": pd.array([False, True], dtype="boolean"),
        "in_window_height": [True, False], "constraint_value_height": [1.01, 0.99], "constraint_level_height": [1.0, 1.0],
        "satisfied_height": pd.array([True, pd.NA], dtype="boolean"),
        "in_window_speed": [True, True], "constraint_value_speed": [0.3, 0.05], "constraint_level_speed": [0.1, 0.1],
        "satisfied_speed": pd.array([False, True], dtype="boolean"),
        "action_before_height": [0.2, None], "action_after_height": [0.2, None], "bound_lo_height": [-0.4, None],
        "bound_hi_height": [np.inf, None], "action_before_speed": [0.9, None], "action_after_speed": [0.2, None],
        "bound_lo_speed": [0.0, None], "bound_hi_speed": [0.25, None],
    })
    captions = step_captions("height=high,speed=low", steps)
    assert captions[0].startswith("t=0 height=high in window  +0.010 >= 0 ok | speed=low in window  +0.200 <= 0\n")
    assert captions[0].endswith("height act +0.20->+0.20 in [-0.40, +inf] | speed act +0.90->+0.20 in [+0.00, +0.25]")
    assert captions[1] == "t=1 height=high after window  -0.010 >= 0 | speed=low in window  -0.050 <= 0 ok"
