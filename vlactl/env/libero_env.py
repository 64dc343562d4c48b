"""One LIBERO task as an environment: reset to a fixed initial state, settle, step, render only on demand.

Images are rendered only when a caller asks (`step(..., render=True)` or `render()`), so rollouts whose policy needs
no images, and the scripted expert's dry runs, pay for physics alone (~20 ms a step instead of ~60 ms).

Rendering runs on the CPU (Mesa llvmpipe), where the cost is per triangle, not per pixel: the spatial scenes carry
~300k triangles (bowls 42k each, the robot ~130k, its pedestal 33k). `EnvConfig` holds the levers that cut a step with
both 128 px cameras from ~160 ms to ~60 ms on one core; `benchmarks/bench_env.py` measures them.
"""

from __future__ import annotations

import contextlib
import io
import logging
from dataclasses import dataclass, field

import numpy as np

from vlactl.env import features
from vlactl.env.suites import MAX_STEPS, TaskInfo, init_states, task_info
from vlactl.errors import check_non_negative, check_positive

CAMERAS = ("agentview", "robot0_eye_in_hand")
IMAGE_KEYS = {"agentview": "image", "robot0_eye_in_hand": "wrist_image"}
GRIPPER_COMMAND = {"open": -1.0, "closed": 1.0}  # LIBERO's gripper action for each state
NOOP_ACTION = np.array([0, 0, 0, 0, 0, 0, GRIPPER_COMMAND["open"]], dtype=np.float64)  # hold still, gripper open


@dataclass(frozen=True)
class EnvConfig:
    """Simulator and render settings. Policies must be trained and evaluated with the same render settings: all but
    `cull_offscreen` change the pixels."""

    image_size: int = 128
    settle_steps: int = 10
    reflections: bool = False  # off: ~40% cheaper renders
    shadows: bool = True  # no LIBERO light casts shadows, so this costs nothing either way
    skybox: bool = True
    # Offscreen multisampling. MuJoCo's default 4 doubles llvmpipe's time per frame (agentview 80 -> 41 ms CPU on
    # libero_spatial); 0 leaves slightly jagged edges at 128 px.
    msaa_samples: int = 0
    # Skip geoms whose bounding sphere lies outside the camera's view: pixel-identical images; the wrist camera sees
    # a third fewer triangles (wrist render 34 -> 25 ms, agentview ~unchanged).
    cull_offscreen: bool = True
    # Draw visual-only meshes of more than 10k triangles (bowls, pedestal, robot links, objects; not the gripper)
    # simplified by vertex clustering on a grid of this many millimetres: 2 mm is under a pixel in the agent view and
    # cuts libero_spatial from 293k to 200k triangles (both renders 64 -> 42 ms). 0 draws the full meshes. Physics
    # and collision meshes are untouched.
    mesh_cell_mm: float = 2.0


def check_env_config(settings: dict) -> None:
    """Check a stage's `env` settings before any worker builds a simulator from them."""
    cfg = EnvConfig(**settings)
    check_positive("env.image_size", cfg.image_size)
    for key in ("settle_steps", "msaa_samples", "mesh_cell_mm"):
        check_non_negative(f"env.{key}", getattr(cfg, key))


@dataclass
class Observation:
    """What a policy or a logger gets each step."""

    state: np.ndarray  # (7,) SPEC.md §2 robot state (x, y, z, roll, pitch, yaw, gripper aperture)
    libero_state: np.ndarray  # (8,) eef pos, axis-angle, finger qpos (LIBERO / openpi convention)
    raw: dict  # LIBERO's observation dict without images (object poses etc.)
    images: dict[str, np.ndarray] = field(default_factory=dict)  # "image", "wrist_image": HxWx3 uint8, upright
    # where the object the task moves is (the first goal predicate's object; NaN when that names no object, e.g. a
    # drawer region): the step table's object_x/y/z, which show whether an intervention knocked it away
    object_pos: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))


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
        first = self.goal[0]
        self._moved_object = first[1] if len(first) > 1 else None
        self._render_setup_for = None  # the MjrContext the one-time render settings were applied to

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

    def reset(self, init_state: int, seed: int = 0, render: bool = False, gripper: str = "open") -> Observation:
        """Reset to the suite's init state `init_state`, then settle with no-op steps that hold the gripper `open`
        (LIBERO's protocol) or `closed` (the paper's baselines under gripper=closed start that way).

        NumPy's global RNG is seeded right before the reset: LIBERO re-samples fixture placements from it and
        `set_init_state` does not restore them, so this makes (task, init state, seed) reproducible.
        """
        if not 0 <= init_state < len(self._init_states):
            from vlactl.errors import UsageError

            raise UsageError(f"init state {init_state} out of range; allowed: 0..{len(self._init_states) - 1}")
        self.env.seed(seed)
        np.random.seed(seed)
        self.env.reset()
        # A soft reset keeps the gripper's command state (robosuite sets it only when building the model), so without
        # this a reset's settle steps depend on the previous episode (states differed by up to 3 cm).
        for robot in self.env.robots:
            robot.gripper.current_action = np.zeros(robot.gripper.dof)
        self._configure_renderer()
        raw = self.env.set_init_state(self._init_states[init_state])
        settle = NOOP_ACTION.copy()
        settle[-1] = GRIPPER_COMMAND[gripper]
        for _ in range(self.cfg.settle_steps):
            raw, *_ = self.env.step(settle)
        return self._observe(raw, render)

    def step(self, action, render: bool = False) -> tuple[Observation, bool]:
        """Apply a 7-D action in [-1, 1]; returns the observation and LIBERO's own success check."""
        raw, _, _, _ = self.env.step(np.asarray(action, dtype=np.float64))
        return self._observe(raw, render), self.success()

    def success(self) -> bool:
        return bool(self.env.check_success())

    def render(self) -> dict[str, np.ndarray]:
        """Both cameras, upright (LIBERO's images come upside down: flip both axes, as openpi and OpenVLA do)."""
        ctx = self.env.sim._render_context_offscreen
        if self._render_setup_for is not ctx.con:
            self._configure_renderer()
        # robosuite never re-binds its GL context; with two envs in one process the newest one would be current.
        ctx.gl_ctx.make_current()
        out = {}
        for cam in CAMERAS:
            img = self._render_camera(ctx, cam)
            out[IMAGE_KEYS[cam]] = np.ascontiguousarray(img[::-1, ::-1])
        return out

    def _render_camera(self, ctx, cam: str) -> np.ndarray:
        """robosuite's `sim.render` without its lock and resize checks, plus frustum culling."""
        import mujoco

        m, d = self.env.sim.model._model, self.env.sim.data._data
        size = self.cfg.image_size
        cam_id = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_CAMERA, cam)
        ctx.cam.type = mujoco.mjtCamera.mjCAMERA_FIXED
        ctx.cam.fixedcamid = cam_id
        groups = m.geom_group
        saved = groups.copy()
        if self.cfg.cull_offscreen:
            # Move geoms the camera cannot see to a group the scene hides, for this scene update only.
            groups[~_in_frustum(m, d, cam_id)] = self._hidden_group
        try:
            mujoco.mjv_updateScene(m, d, ctx.vopt, ctx.pert, ctx.cam, mujoco.mjtCatBit.mjCAT_ALL, ctx.scn)
        finally:
            groups[:] = saved
        viewport = mujoco.MjrRect(0, 0, size, size)
        mujoco.mjr_render(viewport, ctx.scn, ctx.con)
        img = np.empty((size, size, 3), dtype=np.uint8)
        mujoco.mjr_readPixels(img, None, viewport, ctx.con)
        return img

    def _observe(self, raw: dict, render: bool) -> Observation:
        self._last_raw = raw
        pos, quat, grip = raw["robot0_eef_pos"], raw["robot0_eef_quat"], raw["robot0_gripper_qpos"]
        moved = raw.get(f"{self._moved_object}_pos") if self._moved_object else None
        return Observation(
            state=features.robot_state(pos, quat, grip),
            libero_state=features.libero_state(pos, quat, grip),
            raw=raw,
            images=self.render() if render else {},
            object_pos=np.full(3, np.nan) if moved is None else np.asarray(moved, dtype=np.float64),
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
        if self._render_setup_for is ctx.con:
            return
        # Once per GL context: robosuite creates it (with MuJoCo's defaults) inside the env's constructor.
        m, con, size = self.env.sim.model._model, ctx.con, self.cfg.image_size
        ctx.gl_ctx.make_current()
        if con.offSamples != self.cfg.msaa_samples:
            # The offscreen buffers take the sample count when (re)allocated, and mjr_resizeOffscreen reallocates only
            # on a size change: without the detour, readPixels skips the MSAA resolve and returns garbage.
            con.offSamples = self.cfg.msaa_samples
            mujoco.mjr_resizeOffscreen(size + 1, size, con)
        mujoco.mjr_resizeOffscreen(size, size, con)  # robosuite allocates 640x480; we never read more than this
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, con)
        if self.cfg.mesh_cell_mm > 0:
            _upload_simplified_meshes(m, con, self.cfg.mesh_cell_mm / 1000)
        self._hidden_group = int(np.flatnonzero(np.asarray(ctx.vopt.geomgroup) == 0)[-1])
        self._render_setup_for = con

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.env.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _in_frustum(m, d, cam_id: int, aspect: float = 1.0) -> np.ndarray:
    """Per geom: may its bounding sphere intersect the camera's view frustum? Conservative (1% slack)."""
    rot = d.cam_xmat[cam_id].reshape(3, 3)  # columns: camera x (right), y (up), z (backwards) in world frame
    local = (d.geom_xpos - d.cam_xpos[cam_id]) @ rot
    x, y, depth = local[:, 0], local[:, 1], -local[:, 2]
    tan_y = np.tan(np.deg2rad(m.cam_fovy[cam_id]) / 2) * 1.01
    tan_x = tan_y * aspect
    r = m.geom_rbound * 1.01 + 1e-3
    inside = (depth > -r) & ((np.abs(x) - tan_x * depth) / np.hypot(1, tan_x) <= r)
    inside &= (np.abs(y) - tan_y * depth) / np.hypot(1, tan_y) <= r
    return inside | (m.geom_rbound <= 0)  # rbound 0: planes, unbounded


MIN_FACES_TO_SIMPLIFY = 10_000  # leaves the gripper (7k, a few cm from the wrist camera) at full detail


def _upload_simplified_meshes(m, con, cell: float) -> None:
    """Re-upload big visual-only meshes to the GL context simplified; the model itself is restored unchanged.

    Vertex clustering: every vertex snaps to the first vertex of its grid cell, collapsed and duplicate triangles go.
    Faces keep their own normals and texture coordinates. Deterministic (depends only on the mesh and `cell`).
    """
    import mujoco

    is_mesh = m.geom_type == mujoco.mjtGeom.mjGEOM_MESH
    colliding = is_mesh & ((m.geom_contype != 0) | (m.geom_conaffinity != 0))
    visual_only = set(m.geom_dataid[is_mesh]) - set(m.geom_dataid[colliding])
    for mesh in sorted(visual_only):
        fa, fn = m.mesh_faceadr[mesh], m.mesh_facenum[mesh]
        if fn <= MIN_FACES_TO_SIMPLIFY:
            continue
        va, vn = m.mesh_vertadr[mesh], m.mesh_vertnum[mesh]
        face, normal, tex = (a[fa : fa + fn].copy() for a in (m.mesh_face, m.mesh_facenormal, m.mesh_facetexcoord))
        keep, snapped = _cluster_faces(m.mesh_vert[va : va + vn], face, cell)
        k = len(keep)
        try:
            m.mesh_face[fa : fa + k] = snapped[keep]
            m.mesh_facenormal[fa : fa + k] = normal[keep]
            m.mesh_facetexcoord[fa : fa + k] = tex[keep]
            m.mesh_facenum[mesh] = k
            mujoco.mjr_uploadMesh(m, con, mesh)
        finally:
            m.mesh_facenum[mesh] = fn
            m.mesh_face[fa : fa + fn], m.mesh_facenormal[fa : fa + fn], m.mesh_facetexcoord[fa : fa + fn] = face, normal, tex


def _cluster_faces(vert: np.ndarray, face: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the faces to keep and all faces with snapped vertex indices."""
    q = np.floor(vert / cell).astype(np.int64)
    q -= q.min(axis=0)
    span = q.max(axis=0) + 1
    key = (q[:, 0] * span[1] + q[:, 1]) * span[2] + q[:, 2]
    _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    snapped = first[inverse.ravel()][face]
    ok = (snapped[:, 0] != snapped[:, 1]) & (snapped[:, 1] != snapped[:, 2]) & (snapped[:, 0] != snapped[:, 2])
    candidates = np.flatnonzero(ok)
    _, unique = np.unique(np.sort(snapped[candidates], axis=1), axis=0, return_index=True)
    return candidates[np.sort(unique)], snapped
