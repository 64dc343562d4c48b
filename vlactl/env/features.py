"""Robot features of SPEC.md §2 from LIBERO proprioception: pure numpy, no simulator."""

from __future__ import annotations

import numpy as np

STATE_FEATURES = ("x", "y", "z", "roll", "pitch", "yaw", "gripper")
ACTION_FEATURES = ("dx", "dy", "dz", "droll", "dpitch", "dyaw", "gripper_action")
TRANSLATION = ("dx", "dy", "dz")
CONTROL_DT = 0.05  # LIBERO runs its controller at 20 Hz
FINGER_OPEN = 0.04  # Panda finger joint travel (m); qpos is (+q, -q)


def action_dimensions(feature: str) -> tuple[int, ...] | None:
    """The action dimensions a feature is a function of: a commanded-action feature its own, speed the translation's;
    None for a feature of the state."""
    if feature in ACTION_FEATURES:
        return (ACTION_FEATURES.index(feature),)
    if feature == "speed":
        return tuple(ACTION_FEATURES.index(f) for f in TRANSLATION)
    return None


def quat_xyzw_to_euler(quat: np.ndarray) -> np.ndarray:
    """Extrinsic x-y-z (roll, pitch, yaw) angles from robosuite's xyzw quaternion."""
    x, y, z, w = np.moveaxis(np.asarray(quat, dtype=np.float64), -1, 0)
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return np.stack([roll, pitch, yaw], axis=-1)


def wrap_orientation(euler: np.ndarray) -> np.ndarray:
    """Wrap each angle into the interval centred on the Panda's working pose, so it never jumps in an episode.

    The gripper points down, so roll sits near ±pi: roll goes to [0, 2pi) (centred on pi); pitch and yaw sit near 0
    and stay in (-pi, pi]. A probe regressing an angle across a 2pi jump would be meaningless.
    """
    euler = np.array(euler, dtype=np.float64, copy=True)
    euler[..., 0] = np.mod(euler[..., 0], 2 * np.pi)
    euler[..., 1:] = np.mod(euler[..., 1:] + np.pi, 2 * np.pi) - np.pi
    return euler


def gripper_aperture(gripper_qpos: np.ndarray) -> np.ndarray:
    """Finger opening normalised to [0, 1] (0 closed, 1 fully open)."""
    q = np.asarray(gripper_qpos, dtype=np.float64)
    return np.clip((q[..., 0] - q[..., 1]) / (2 * FINGER_OPEN), 0.0, 1.0)


def robot_state(eef_pos, eef_quat, gripper_qpos) -> np.ndarray:
    """s = (x, y, z, roll, pitch, yaw, g) of SPEC.md §2."""
    euler = wrap_orientation(quat_xyzw_to_euler(eef_quat))
    g = gripper_aperture(gripper_qpos)[..., None]
    return np.concatenate([np.asarray(eef_pos, dtype=np.float64), euler, g], axis=-1)


def quat_xyzw_to_axis_angle(quat: np.ndarray) -> np.ndarray:
    """Axis-angle vector, as in LIBERO's 8-D state used by openpi and LeRobot."""
    q = np.asarray(quat, dtype=np.float64)
    w = np.clip(q[..., 3], -1.0, 1.0)
    den = np.sqrt(np.maximum(1.0 - w * w, 0.0))
    angle = 2.0 * np.arccos(w)
    safe = den > 1e-8
    scale = np.where(safe, angle / np.where(safe, den, 1.0), 0.0)
    return q[..., :3] * scale[..., None]


def libero_state(eef_pos, eef_quat, gripper_qpos) -> np.ndarray:
    """LIBERO's 8-D state: eef position (3), axis-angle (3), finger joint positions (2)."""
    return np.concatenate(
        [np.asarray(eef_pos, dtype=np.float64), quat_xyzw_to_axis_angle(eef_quat), np.asarray(gripper_qpos, dtype=np.float64)],
        axis=-1,
    )


def axis_angle_to_quat_xyzw(axis_angle: np.ndarray) -> np.ndarray:
    v = np.asarray(axis_angle, dtype=np.float64)
    angle = np.linalg.norm(v, axis=-1, keepdims=True)
    axis = np.divide(v, angle, out=np.zeros_like(v), where=angle > 1e-12)
    return np.concatenate([axis * np.sin(angle / 2), np.cos(angle / 2)], axis=-1)


def robot_state_from_libero(state: np.ndarray) -> np.ndarray:
    """s of SPEC.md §2 from LIBERO's 8-D state (position, axis-angle, finger joints): for datasets that lack it."""
    state = np.asarray(state, dtype=np.float64)
    return robot_state(state[..., :3], axis_angle_to_quat_xyzw(state[..., 3:6]), state[..., 6:8])


def speeds(positions: np.ndarray, dt: float = CONTROL_DT) -> np.ndarray:
    """Speed v_t = ||p_{t+1} - p_t|| / dt of the motion that action t causes (m/s); the last frame repeats."""
    p = np.asarray(positions, dtype=np.float64)
    if len(p) < 2:
        return np.zeros(len(p))
    v = np.linalg.norm(np.diff(p, axis=0), axis=-1) / dt
    return np.append(v, v[-1])
