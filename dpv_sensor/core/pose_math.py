"""Pose and camera-matrix maths on float64 numpy arrays: intrinsics of a resized image, quaternions (x, y, z, w),
4x4 poses, their interpolation and the size of a relative motion. The numpy side of :mod:`dpv_sensor.core.geometry`
(same conventions: OpenCV camera axes, ``T_a_b`` maps frame b to frame a, pixel centres at integer coordinates),
kept apart from it so that what reads bags, messages and odometry does not import torch."""
from __future__ import annotations

import math
from typing import Tuple

import numpy as np

__all__ = ['scale_intrinsics_np', 'pose_delta_np', 'rotation_angle_np', 'relative_pose_error_np', 'quat_angle_deg',
           'quat_to_matrix', 'matrix_to_quat', 'slerp', 'make_pose', 'interpolate_pose']


def scale_intrinsics_np(K_33, sx: float, sy: float) -> np.ndarray:
    """Numpy float64 twin of scale_intrinsics: K for an image scaled by (sx, sy):
    fx' = fx*sx, cx' = (cx + 0.5)*sx - 0.5 (same for y)."""
    K = np.array(K_33, dtype=np.float64, copy=True)
    K[0, 0] *= sx
    K[0, 1] *= sx
    K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    K[1, 1] *= sy
    K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return K


def pose_delta_np(T_world_a_44: np.ndarray, T_world_b_44: np.ndarray) -> Tuple[float, float]:
    """Translation (metres) and rotation angle (degrees) of the relative motion between two poses.

    Both are ``T_world_cam`` (camera-to-world). The translation is the distance between the camera
    centres; the angle is that of ``R_a^T R_b`` (in [0, 180]).
    """
    Ta = np.asarray(T_world_a_44, dtype=np.float64)
    Tb = np.asarray(T_world_b_44, dtype=np.float64)
    translation = float(np.linalg.norm(Tb[:3, 3] - Ta[:3, 3]))
    return translation, math.degrees(rotation_angle_np(Ta[:3, :3].T @ Tb[:3, :3]))


def rotation_angle_np(R_33: np.ndarray) -> float:
    """Rotation angle of a 3x3 rotation matrix in radians, in [0, pi]; the numpy twin of
    :func:`dpv_sensor.core.geometry.rotation_angle` (atan2 form: accurate for small and large angles alike)."""
    R = np.asarray(R_33, dtype=np.float64)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return math.atan2(0.5 * float(np.linalg.norm(v)), 0.5 * (float(np.trace(R)) - 1.0))


def relative_pose_error_np(T_a_44: np.ndarray, T_b_44: np.ndarray) -> Tuple[float, float]:
    """(translation in metres, rotation in degrees) of ``T_a^-1 T_b``: how far pose b is from pose a, measured in
    a's frame (an estimate against its reference, or one relative motion against another)."""
    E = np.linalg.inv(np.asarray(T_a_44, dtype=np.float64)) @ np.asarray(T_b_44, dtype=np.float64)
    return float(np.linalg.norm(E[:3, 3])), math.degrees(rotation_angle_np(E[:3, :3]))


def quat_angle_deg(q0_4: np.ndarray, q1_4: np.ndarray) -> float:
    """Angle in degrees between the rotations of two unit quaternions (either sign)."""
    return math.degrees(2.0 * math.acos(min(1.0, abs(float(np.dot(q0_4, q1_4))))))


def quat_to_matrix(q_xyzw) -> np.ndarray:
    """3x3 rotation of a quaternion (x, y, z, w); normalised first."""
    x, y, z, w = np.asarray(q_xyzw, dtype=np.float64) / np.linalg.norm(q_xyzw)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quat(R_33) -> np.ndarray:
    """Unit quaternion (x, y, z, w), w >= 0, of a rotation matrix (Shepperd's method)."""
    m = np.asarray(R_33, dtype=np.float64)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    cands = np.array([1.0 + tr, 1.0 + m[0, 0] - m[1, 1] - m[2, 2],
                      1.0 - m[0, 0] + m[1, 1] - m[2, 2], 1.0 - m[0, 0] - m[1, 1] + m[2, 2]])
    i = int(np.argmax(cands))
    s = 2.0 * math.sqrt(max(cands[i], 1e-300))
    if i == 0:
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4]
    elif i == 1:
        q = [s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif i == 2:
        q = [(m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4, (m[1, 0] - m[0, 1]) / s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def slerp(q0_xyzw, q1_xyzw, alpha: float) -> np.ndarray:
    """Spherical linear interpolation along the shortest arc (alpha 0 -> q0, 1 -> q1)."""
    q0 = np.asarray(q0_xyzw, dtype=np.float64)
    q1 = np.asarray(q1_xyzw, dtype=np.float64)
    q0 = q0 / np.linalg.norm(q0)
    q1 = q1 / np.linalg.norm(q1)
    dot = float(np.dot(q0, q1))
    if dot < 0.0:
        q1, dot = -q1, -dot
    dot = min(dot, 1.0)
    theta = math.acos(dot)
    if math.sin(theta) < 1e-9:
        q = (1.0 - alpha) * q0 + alpha * q1
    else:
        q = (math.sin((1.0 - alpha) * theta) * q0 + math.sin(alpha * theta) * q1) / math.sin(theta)
    return q / np.linalg.norm(q)


def make_pose(t_xyz, q_xyzw) -> np.ndarray:
    """4x4 float64 transform from a translation and a quaternion (x, y, z, w)."""
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(q_xyzw)
    T[:3, 3] = np.asarray(t_xyz, dtype=np.float64)
    return T


def interpolate_pose(T0_44, T1_44, alpha: float) -> np.ndarray:
    """SLERP rotation + linear translation between two 4x4 poses (alpha 0 -> T0, 1 -> T1)."""
    T0 = np.asarray(T0_44, dtype=np.float64)
    T1 = np.asarray(T1_44, dtype=np.float64)
    q = slerp(matrix_to_quat(T0[:3, :3]), matrix_to_quat(T1[:3, :3]), alpha)
    return make_pose(T0[:3, 3] + alpha * (T1[:3, 3] - T0[:3, 3]), q)
