"""LIBERO datasets as users have them, written by LeRobot's own `LeRobotDataset.create` with LeRobot's key names and
no vlactl-only columns: 256 px cameras stored as images, and cameras stored as video (LeRobot's default). `collect`,
`sweep`, `plot readings` and `train-policy` read both, the images resized to the 128 px the embedded models take;
datasets a model cannot read are one-line errors."""

import shutil

import numpy as np
import pandas as pd
import pytest
from synthetic_demos import user_image, write_user_dataset
from typer.testing import CliRunner

from vlactl.cli import app
from vlactl.data import frames as frames_module
from vlactl.data.frames import load_frames
from vlactl.errors import UsageError
from vlactl.steering.activations import ActivationStore

EPISODES, FRAMES = 4, 6  # episode k has FRAMES + k frames
N = sum(FRAMES + k for k in range(EPISODES))
CAMERAS = ("image", "wrist_image")
KINDS = {"images_256": dict(size=256, video=False), "video_128": dict(size=128, video=True)}


@pytest.fixture(scope="module", params=list(KINDS))
def dataset(request, tmp_path_factory):
    root = tmp_path_factory.mktemp(request.param) / "libero"
    return write_user_dataset(root, episodes=EPISODES, frames=FRAMES, **KINDS[request.param]), KINDS[request.param]


def expected_images(size: int) -> np.ndarray:
    """[N, cams, 128, 128, 3]: what was stored, resized to 128 px."""
    return np.stack([[frames_module._fit(user_image(i, size, cam)[None], (128, 128))[0] for cam in CAMERAS]
                     for i in range(N)])


def test_frames_are_decoded_resized_and_cached_once(dataset, tmp_path, monkeypatch):
    root, kind = dataset
    frames = load_frames(root, CAMERAS, tmp_path / "cache", image_size=128)
    assert frames.images.shape == (N, 2, 128, 128, 3) and len(frames.tasks) == 2
    error = np.abs(np.asarray(frames.images, dtype=int) - expected_images(kind["size"]))
    if kind["video"]:  # lossy AV1: within a few levels, and every row holds its own frame (6 red levels apart)
        assert error.mean() < 2.5 and error.max() <= 12
        red = frames.images[:, 0, ..., 0].reshape(N, -1).mean(1)
        assert np.round((red - red[0]) / 6).astype(int).tolist() == list(range(N))
    else:
        assert error.max() == 0
    for reader in ("_image_batches", "_video_batches"):  # a second load reads the cache alone
        monkeypatch.setattr(frames_module, reader, lambda *args: pytest.fail("decoded twice"))
    assert np.array_equal(load_frames(root, CAMERAS, tmp_path / "cache", image_size=128).images, frames.images)


def test_collect_sweep_plot_readings_and_train_policy_read_them(dataset, tmp_path):
    root, _ = dataset
    runner = CliRunner()
    common = [f"dataset={root}", f"cache_dir={tmp_path / 'cache'}", "threads=1"]

    def run(*args, on_dataset=True):
        result = runner.invoke(app, [*args, *(common if on_dataset else [])])
        assert result.exit_code == 0, result.output

    run("collect", "model=random", f"output_dir={tmp_path / 'acts'}")
    labels = ActivationStore(tmp_path / "acts").labels
    assert len(labels) == N and (labels["init_state"] == -1).all()  # labels derived from the 8-D state
    run("train-probes", f"activations={tmp_path / 'acts'}", f"output_dir={tmp_path / 'probes'}",
        "features=[gripper_action,dx]", "cv_folds=2", "robustness_directions=2", on_dataset=False)
    run("sweep", "model=random", f"output_dir={tmp_path / 'sweep'}", "direction=ones", "frames=4", "alphas=[2]",
        "layers=[backbone.0]")
    assert len(pd.read_parquet(tmp_path / "sweep" / "sweep.parquet")) == 4
    run("plot", "readings", "model=random", f"probes={tmp_path / 'probes'}", "frames=4", "zmin=-4", "zmax=-3",
        f"output_dir={tmp_path / 'fig'}", "formats=[png]")
    assert len(pd.read_parquet(tmp_path / "fig" / "readings.parquet")) == 3 * 4
    run("train-policy", "model=hybrid", f"output_dir={tmp_path / 'policy'}", "steps=1", "batch_size=4",
        "warmup_steps=1", "model.vision_channels=[8,8,8]", "model.width=32", "model.layers=2", "model.heads=2",
        "model.kv_heads=1", "model.head_dim=16", "model.mlp_width=64", "model.expert_width=32",
        "model.expert_mlp_width=64")
    assert (tmp_path / "policy" / "checkpoint" / "model.safetensors").is_file()


@pytest.mark.parametrize("write, message", [
    (dict(cameras=("front", "wrist")), r"it has observation\.images\.front \(image\), observation\.images\.wrist "
     r"\(image\), observation\.state \[8\], action \[7\]; the model needs observation\.images\.image \(image or "
     r"video\), observation\.images\.wrist_image \(image or video\), observation\.state \[8\], action \[7\]$"),
    (dict(state_dim=9), r"it has .*observation\.state \[9\], action \[7\]; the model needs .*observation\.state \[8\]"),
])
def test_a_dataset_the_model_cannot_read_is_one_line(tmp_path, write, message):
    root = write_user_dataset(tmp_path / "other", size=32, episodes=1, frames=2, **write)
    with pytest.raises(UsageError, match=message) as error:
        load_frames(root, CAMERAS, tmp_path / "cache", image_size=128)
    assert "\n" not in str(error.value)


def test_a_video_shorter_than_its_episodes_is_one_line(tmp_path):
    root = write_user_dataset(tmp_path / "short", size=32, video=True, episodes=2, frames=2)
    other = write_user_dataset(tmp_path / "one", size=32, video=True, episodes=1, frames=2)
    video = "videos/observation.images.wrist_image/chunk-000/file-000.mp4"
    shutil.copy(other / video, root / video)  # the first episode's frames only
    with pytest.raises(UsageError, match=r"file-000\.mp4' has no frame at 0\.200 s \(episode 1\)"):
        load_frames(root, CAMERAS, tmp_path / "cache", image_size=128)
