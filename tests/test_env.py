"""LiberoEnv: images, determinism, on-demand rendering, errors. One shared env (~5 s to build) plus one more."""

import subprocess
import sys

import numpy as np
import pytest

import vlactl.env  # noqa: F401  (MUJOCO_GL before MuJoCo loads)
from vlactl.env.libero_env import EnvConfig, LiberoEnv, _cluster_faces
from vlactl.errors import UsageError

SUITE, TASK = "libero_spatial", 0


def _actions(n):
    """Back and forth with the gripper closing halfway through: exercises arm, fingers and both cameras."""
    return [np.array([0.5 * np.sin(i / 3), -0.3 * np.cos(i / 3), 0.2, 0, 0, 0, 1 if i > n // 2 else -1]) for i in range(n)]


@pytest.fixture(scope="module")
def env():
    with LiberoEnv(SUITE, TASK, render=True) as e:
        yield e


def test_reset_images_upright(env):
    obs = env.reset(0, render=True)
    assert set(obs.images) == {"image", "wrist_image"}
    for img in obs.images.values():
        assert img.shape == (128, 128, 3) and img.dtype == np.uint8
    agent, wrist = (obs.images[k].astype(float) for k in ("image", "wrist_image"))
    # Upright: the agent view has the wall at the top and the bright table at the bottom; the wrist view has the
    # table at the top and the dark gripper at the bottom.
    assert agent[-16:].mean() > agent[:16].mean() + 30
    assert wrist[:16].mean() > wrist[-16:].mean() + 30


def test_culling_keeps_pixels_and_renders_are_repeatable(env):
    env.reset(0)
    for action in _actions(6):
        obs, _ = env.step(action, render=True)
        # robosuite's own render path draws every geom (no culling), upside down, with the same GL settings.
        for cam, key in (("agentview", "image"), ("robot0_eye_in_hand", "wrist_image")):
            raw = env.env.sim.render(width=128, height=128, camera_name=cam)
            np.testing.assert_array_equal(raw[::-1, ::-1], obs.images[key])
        again = env.render()
        for key in obs.images:
            np.testing.assert_array_equal(again[key], obs.images[key])


def test_step_without_render_has_no_images(env):
    env.reset(0)
    obs, success = env.step(np.zeros(7))
    assert obs.images == {}
    assert obs.state.shape == (7,) and isinstance(success, bool)


@pytest.mark.parametrize("bad", [-1, 50, 10_000])
def test_bad_init_state_is_a_usage_error(env, bad):
    with pytest.raises(UsageError, match="init state"):
        env.reset(bad)


def test_same_inputs_same_images_and_states_across_envs(env):
    # The shared env has run other episodes first (gripper closed, arm moved): a reset must not depend on that.
    env.reset(3, seed=1)
    for action in _actions(10):
        env.step(action)
    with LiberoEnv(SUITE, TASK, render=True) as fresh:
        runs = []
        for e in (env, fresh):
            obs = e.reset(3, seed=7, render=True)
            trace = [obs]
            for action in _actions(12):
                trace.append(e.step(action, render=True)[0])
            runs.append(trace)
    for a, b in zip(*runs):
        np.testing.assert_array_equal(a.libero_state, b.libero_state)
        np.testing.assert_array_equal(a.raw["akita_black_bowl_1_pos"], b.raw["akita_black_bowl_1_pos"])
        for key in a.images:
            np.testing.assert_array_equal(a.images[key], b.images[key])


@pytest.mark.slow
def test_render_settings_change_pixels_not_physics():
    # Full meshes with MuJoCo's 4x MSAA vs the project's defaults: same states, similar but not identical images.
    with LiberoEnv(SUITE, TASK, EnvConfig(msaa_samples=4, cull_offscreen=False, mesh_cell_mm=0), render=True) as stock:
        with LiberoEnv(SUITE, TASK, render=True) as fast:
            a, b = stock.reset(0, render=True), fast.reset(0, render=True)
            np.testing.assert_array_equal(a.libero_state, b.libero_state)
            for key in a.images:
                diff = np.abs(a.images[key].astype(int) - b.images[key]).mean()
                assert 0 < diff < 8, (key, diff)



def test_cluster_faces_keeps_coarse_meshes_and_collapses_fine_ones():
    # A 10x10 grid of 1 mm squares (200 triangles) in the z=0 plane.
    xs, ys = np.meshgrid(np.arange(11), np.arange(11), indexing="ij")
    vert = np.stack([xs.ravel(), ys.ravel(), np.zeros(121)], axis=1) * 1e-3
    idx = np.arange(121).reshape(11, 11)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel()
    face = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    keep, snapped = _cluster_faces(vert, face, 1e-4)  # cells smaller than the spacing: nothing changes
    assert len(keep) == 200 and np.array_equal(snapped, face)
    keep, snapped = _cluster_faces(vert, face, 2.5e-3)  # 2.5 mm cells: ~1/6 of the triangles survive
    assert 0 < len(keep) < 60
    assert all(len(set(f)) == 3 for f in snapped[keep])
    keep, _ = _cluster_faces(vert, face, 1.0)  # one cell: everything collapses
    assert len(keep) == 0


def test_torchvision_imports_after_a_render_context():
    """triton (loaded by `import torchvision` through torch._dynamo) segfaulted once Mesa had made a GL context."""
    code = (
        "from vlactl.env.libero_env import LiberoEnv\n"
        f"with LiberoEnv({SUITE!r}, {TASK}, render=True) as env:\n    env.reset(0, render=True)\n"
        "import torchvision\n"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]


def test_robosuite_macro_notice_is_dropped():
    """robosuite's three-line 'no private macro file' warning, printed by every worker, is filtered out."""
    res = subprocess.run([sys.executable, "-c", "import vlactl.env, robosuite"], capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "macro" not in res.stderr
