"""One LIBERO task as an environment: reset to a fixed initial state, settle, step, render only on demand.

Images are rendered only when a caller asks (`step(..., render=True)` or `render()`), so rollouts whose policy needs
no images, and the scripted expert's dry runs, pay for physics alone (~18 ms a step instead of ~250 ms).
"""

from __future__ import annotations

import contextlib
import io
import logging
from dataclasses import dataclass, field

import numpy as np

from vlactl.env import features
from vlactl.env.suites import MAX_STEPS, TaskInfo, init_states, task_info

CAMERAS = ("agentview", "robot0_eye_in_hand")
IMAGE_KEYS = {"agentview": "image", "robot0_eye_in_hand": "wrist_image"}
NOOP_ACTION = np.array([0, 0, 0, 0, 0, 0, -1], dtype=np.float64)  # hold still, gripper open


@dataclass(frozen=True)
class EnvConfig:
    image_size: int = 128
    settle_steps: int = 10
    reflections: bool = False  # off: ~40% cheaper renders; policies must be trained and run with the same setting
    shadows: bool = True
    skybox: bool = True


@dataclass
class Observation:
    """What a policy or a logger gets each step."""

    state: np.ndarray  # (7,) SPEC.md §2 robot state (x, y, z, roll, pitch, yaw, gripper aperture)
    libero_state: np.ndarray  # (8,) eef pos, axis-angle, finger qpos (LIBERO / openpi convention)
    raw: dict  # LIBERO's observation dict without images (object poses etc.)
    images: dict[str, np.ndarray] = field(default_factory=dict)  # "image", "wrist_image": HxWx3 uint8, upright


class LiberoEnv:
    def __init__(self, suite: str, task_id: int, cfg: EnvConfig = EnvConfig(), render: bool = True):
        from libero.libero.envs.env_wrapper import ControlEnv

        logging.getLogger("robosuite").setLevel(logging.ERROR)
        self.cfg = cfg
        self.task: TaskInfo = task_info(suite, task_id)
        self.max_steps = MAX_STEPS[suite]
        self._init_states = init_states(suite, task_id)
        self._renders = render
        with contextlib.redirect_stdout(io.StringIO()):
            self.env = ControlEnv(
                bddl_file_name=self.task.bddl_file,
                camera_heights=cfg.image_size,
                camera_widths=cfg.image_size,
                use_camera_obs=False,  # we render on demand instead of every step
                has_offscreen_renderer=render,
                hard_reset=False,
            )
        self._last_raw: dict = {}

    @property
    def instruction(self) -> str:
        return self.task.instruction

    @property
    def goal(self) -> list:
        """BDDL goal predicates, e.g. [['on', 'akita_black_bowl_1', 'plate_1']]."""
        return self.env.env.parsed_problem["goal_state"]

    @property
    def n_init_states(self) -> int:
        return len(self._init_states)

    def reset(self, init_state: int, seed: int = 0, render: bool = False) -> Observation:
        """Reset to the suite's init state `init_state`, then settle with no-op steps.

        NumPy's global RNG is seeded right before the reset: LIBERO re-samples fixture placements from it and
        `set_init_state` does not restore them, so this makes (task, init state, seed) reproducible.
        """
        if not 0 <= init_state < len(self._init_states):
            from vlactl.errors import UsageError

            raise UsageError(f"init state {init_state} out of range; allowed: 0..{len(self._init_states) - 1}")
        self.env.seed(seed)
        np.random.seed(seed)
        self.env.reset()
        self._configure_renderer()
        raw = self.env.set_init_state(self._init_states[init_state])
        for _ in range(self.cfg.settle_steps):
            raw, *_ = self.env.step(NOOP_ACTION)
        return self._observe(raw, render)

    def step(self, action, render: bool = False) -> tuple[Observation, bool]:
        """Apply a 7-D action in [-1, 1]; returns the observation and LIBERO's own success check."""
        raw, _, _, _ = self.env.step(np.asarray(action, dtype=np.float64))
        return self._observe(raw, render), self.success()

    def success(self) -> bool:
        return bool(self.env.check_success())

    def render(self) -> dict[str, np.ndarray]:
        """Both cameras, upright (LIBERO's images come upside down: flip both axes, as openpi and OpenVLA do)."""
        size = self.cfg.image_size
        sim = self.env.sim
        out = {}
        for cam in CAMERAS:
            img = sim.render(width=size, height=size, camera_name=cam)
            out[IMAGE_KEYS[cam]] = np.ascontiguousarray(img[::-1, ::-1])
        return out

    def _observe(self, raw: dict, render: bool) -> Observation:
        self._last_raw = raw
        pos, quat, grip = raw["robot0_eef_pos"], raw["robot0_eef_quat"], raw["robot0_gripper_qpos"]
        return Observation(
            state=features.robot_state(pos, quat, grip),
            libero_state=features.libero_state(pos, quat, grip),
            raw=raw,
            images=self.render() if render else {},
        )

    def _configure_renderer(self) -> None:
        ctx = getattr(self.env.sim, "_render_context_offscreen", None)
        if ctx is None:
            return
        import mujoco

        flags = ctx.scn.flags
        flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = int(self.cfg.reflections)
        flags[mujoco.mjtRndFlag.mjRND_SHADOW] = int(self.cfg.shadows)
        flags[mujoco.mjtRndFlag.mjRND_SKYBOX] = int(self.cfg.skybox)

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.env.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
