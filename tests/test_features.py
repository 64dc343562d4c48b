import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from vlactl.env import features


def _quat_from_euler(roll, pitch, yaw):
    """xyzw quaternion of R = Rz(yaw) Ry(pitch) Rx(roll)."""
    cr, sr = np.cos(roll / 2), np.sin(roll / 2)
    cp, sp = np.cos(pitch / 2), np.sin(pitch / 2)
    cy, sy = np.cos(yaw / 2), np.sin(yaw / 2)
    return np.array([
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
        cr * cp * cy + sr * sp * sy,
    ])


@settings(max_examples=200, deadline=None)
@given(st.floats(-3.1, 3.1), st.floats(-1.5, 1.5), st.floats(-3.1, 3.1))
def test_euler_round_trip(roll, pitch, yaw):
    got = features.quat_xyzw_to_euler(_quat_from_euler(roll, pitch, yaw))
    np.testing.assert_allclose(got, [roll, pitch, yaw], atol=1e-6)


def test_orientation_wraps_around_the_downward_pose():
    # The Panda points down: roll crosses +-pi. Wrapped, a small wobble around pi stays continuous.
    rolls = np.array([np.pi - 0.01, -np.pi + 0.01])
    euler = np.stack([rolls, np.zeros(2), np.zeros(2)], axis=-1)
    wrapped = features.wrap_orientation(euler)
    assert np.all((wrapped[:, 0] >= 0) & (wrapped[:, 0] < 2 * np.pi))
    assert abs(wrapped[1, 0] - wrapped[0, 0]) < 0.05
    np.testing.assert_allclose(features.wrap_orientation([[0.0, 2 * np.pi + 0.1, -0.1]])[0, 1:], [0.1, -0.1])


def test_gripper_aperture_is_normalised():
    np.testing.assert_allclose(features.gripper_aperture([[0.04, -0.04], [0.0, 0.0], [0.02, -0.02]]), [1.0, 0.0, 0.5])
    assert features.gripper_aperture([0.05, -0.05]) == 1.0


def test_axis_angle_of_half_turn_about_x():
    np.testing.assert_allclose(features.quat_xyzw_to_axis_angle([1.0, 0, 0, 0]), [np.pi, 0, 0], atol=1e-9)
    np.testing.assert_allclose(features.quat_xyzw_to_axis_angle([0, 0, 0, 1.0]), [0, 0, 0])


def test_speed_is_displacement_over_dt():
    p = np.array([[0, 0, 0], [0.003, 0.004, 0], [0.003, 0.004, 0.01]])
    np.testing.assert_allclose(features.speeds(p, dt=0.05), [0.1, 0.2, 0.2])
