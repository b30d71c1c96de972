"""NED/FRD <-> ENU/FLU conversions."""

import math

import numpy as np
import pytest

from drivers.ned_enu import (attitude_enu_to_ned, attitude_ned_to_enu, enu_to_ned, frd_to_flu, ned_to_enu,
                            quat_to_rot, rot_to_quat, yaw_enu_to_ned, yaw_ned_to_enu)


def yaw_quat(yaw):
    return np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])


def test_vectors_swap_north_east_and_flip_down():
    np.testing.assert_allclose(ned_to_enu([1.0, 2.0, 3.0]), [2.0, 1.0, -3.0])
    np.testing.assert_allclose(enu_to_ned(ned_to_enu([0.3, -4.0, 7.0])), [0.3, -4.0, 7.0])
    np.testing.assert_allclose(frd_to_flu([0.1, 0.2, 0.3]), [0.1, -0.2, -0.3])


@pytest.mark.parametrize("yaw_enu", [0.0, 0.7, -2.0, math.pi / 2])
def test_level_attitude_maps_heading(yaw_enu):
    q_ned = attitude_enu_to_ned(yaw_quat(yaw_enu))
    yaw_ned = math.atan2(2 * (q_ned[0] * q_ned[3] + q_ned[1] * q_ned[2]), 1 - 2 * (q_ned[2] ** 2 + q_ned[3] ** 2))
    assert math.remainder(yaw_ned - yaw_enu_to_ned(yaw_enu), 2 * math.pi) == pytest.approx(0.0, abs=1e-9)
    assert yaw_ned_to_enu(yaw_enu_to_ned(yaw_enu)) == pytest.approx(math.remainder(yaw_enu, 2 * math.pi))


def test_facing_east_is_ned_heading_90_degrees_and_a_body_vector_keeps_its_world_direction():
    assert yaw_enu_to_ned(0.0) == pytest.approx(math.pi / 2)
    rng = np.random.default_rng(0)
    for _ in range(50):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        b_flu = rng.normal(size=3)
        world_enu = quat_to_rot(q) @ b_flu
        world_ned = quat_to_rot(attitude_enu_to_ned(q)) @ frd_to_flu(b_flu)
        np.testing.assert_allclose(ned_to_enu(world_ned), world_enu, atol=1e-12)
        np.testing.assert_allclose(attitude_ned_to_enu(attitude_enu_to_ned(q)), q if q[0] >= 0 else -q, atol=1e-12)
        np.testing.assert_allclose(quat_to_rot(rot_to_quat(quat_to_rot(q))), quat_to_rot(q), atol=1e-12)
