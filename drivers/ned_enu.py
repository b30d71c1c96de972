"""Frame conversions between MAVLink/PX4 conventions and the mission's.

MAVLink local frames are NED (x north, y east, z down) with FRD bodies (x forward, y right,
z down); the mission, the plants and the controllers use ENU (X east, Y north, Z up) with FLU
bodies (x forward, y left, z up). Both swaps are their own inverses:

    v_ENU = T v_NED,   T = [[0, 1, 0], [1, 0, 0], [0, 0, -1]]
    w_FLU = B w_FRD,   B = diag(1, -1, -1)
    R_ENU<-FLU = T R_NED<-FRD B

Quaternions are [w, x, y, z], body to world (Hamilton convention).
"""

from __future__ import annotations

import math

import numpy as np

T_ENU_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
B_FLU_FRD = np.diag([1.0, -1.0, -1.0])


def ned_to_enu(v) -> np.ndarray:
    """A position, velocity or acceleration (3,) from NED to ENU (also ENU to NED: T is its own inverse)."""
    v = np.asarray(v, dtype=float)
    return np.array([v[1], v[0], -v[2]])


enu_to_ned = ned_to_enu


def frd_to_flu(w) -> np.ndarray:
    """A body vector (3,), e.g. angular rates, from FRD to FLU (and back)."""
    w = np.asarray(w, dtype=float)
    return np.array([w[0], -w[1], -w[2]])


flu_to_frd = frd_to_flu


def quat_to_rot(q) -> np.ndarray:
    """Rotation matrix (3, 3) of a unit quaternion [w, x, y, z]."""
    w, x, y, z = (float(c) for c in q)
    return np.array([
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
        [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
        [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)],
    ])


def rot_to_quat(R) -> np.ndarray:
    """Unit quaternion [w, x, y, z] (w >= 0) of a rotation matrix (Shepperd's method)."""
    R = np.asarray(R, dtype=float)
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr > 0.0:
        s = 2.0 * math.sqrt(1.0 + tr)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return -q if q[0] < 0.0 else q


def attitude_ned_to_enu(q_ned_frd) -> np.ndarray:
    """Attitude quaternion FRD->NED to FLU->ENU (and back: the map is its own inverse)."""
    return rot_to_quat(T_ENU_NED @ quat_to_rot(q_ned_frd) @ B_FLU_FRD)


attitude_enu_to_ned = attitude_ned_to_enu


def yaw_ned_to_enu(yaw: float) -> float:
    """Heading from north clockwise (NED yaw) to from east counter-clockwise (ENU yaw), wrapped (and back)."""
    return math.remainder(0.5 * math.pi - float(yaw), 2.0 * math.pi)


yaw_enu_to_ned = yaw_ned_to_enu
