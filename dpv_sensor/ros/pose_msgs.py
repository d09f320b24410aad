"""ROS pose messages <-> 4x4 numpy transforms: geometry_msgs Pose / PoseStamped / Transform and nav_msgs/Odometry
(its pose and twist covariance checked by ``dpv_sensor.core.odometry_covariance``). Like ``msgs``, decoders read
fields only (rclpy or rosbags messages) and builders take a ``MessageTypes`` flavour; no rclpy import.
Quaternions are (x, y, z, w) as in ROS; a 4x4 ``T_a_b`` maps points in frame b to frame a."""
from __future__ import annotations

import numpy as np

from dpv_sensor.core.pose_math import make_pose, matrix_to_quat
from dpv_sensor.core.odometry_covariance import CovarianceCheck, check_covariance
from dpv_sensor.ros.msgs import ROS, BadOdometry, BadTransform, MessageTypes, f64_values, header_for


def _checked_pose(xyz, q_xyzw, what: str, names: tuple[str, str], error: type) -> np.ndarray:
    """4x4 from a translation and a quaternion (x, y, z, w) of a message; `error` (naming `what` and the two fields
    `names`) for NaN / inf or a quaternion whose norm is off 1 by more than 1e-3."""
    t = np.array([xyz.x, xyz.y, xyz.z], dtype=np.float64)
    q = np.array([q_xyzw.x, q_xyzw.y, q_xyzw.z, q_xyzw.w], dtype=np.float64)
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(q))):
        raise error(f'{what} has NaN/inf: {names[0]} {t.tolist()}, {names[1]} {q.tolist()}')
    n = float(np.linalg.norm(q))
    if abs(n - 1.0) > 1e-3:
        raise error(f'{what} {names[1]} is not a unit quaternion (norm {n:.6g})')
    return make_pose(t, q)           # make_pose normalises the quaternion


def _pose_fields_to_matrix(pose, what: str) -> np.ndarray:
    return _checked_pose(pose.position, pose.orientation, what, ('position', 'orientation'), BadOdometry)


def transform_to_matrix(tf) -> np.ndarray:
    """geometry_msgs/Transform -> 4x4; BadTransform for NaN / inf or a quaternion that is not unit length."""
    return _checked_pose(tf.translation, tf.rotation, 'transform', ('translation', 'rotation'), BadTransform)


def odometry_to_matrix(msg) -> np.ndarray:
    """nav_msgs/Odometry -> 4x4 T_world_base (header.frame_id <- child_frame_id). Raises BadOdometry."""
    return _pose_fields_to_matrix(msg.pose.pose, 'odometry')


def odometry_covariance(msg) -> np.ndarray | None:
    """The pose covariance of a nav_msgs/Odometry as 6x6 (x, y, z, rotation about x, y, z), or None when the
    publisher did not fill it (all zeros, or -1 for unknown) or it is not a covariance (NaN or infinity, a negative
    variance, asymmetric, not positive semi-definite: ``odometry_covariance_checks`` says which)."""
    return odometry_covariance_checks(msg)[0].matrix_66


def odometry_covariance_checks(msg) -> tuple[CovarianceCheck, CovarianceCheck]:
    """A nav_msgs/Odometry's pose and twist covariance, each checked (``dpv_sensor.core.odometry_covariance``:
    the usable 6x6, or why not)."""
    return check_covariance(msg.pose.covariance), check_covariance(msg.twist.covariance)


def pose_msg_to_matrix(pose) -> np.ndarray:
    """geometry_msgs/Pose (or PoseStamped) -> 4x4. Raises BadOdometry for NaN / non-unit quaternions."""
    return _pose_fields_to_matrix(getattr(pose, 'pose', pose), 'pose')


def _pose_msg(T_44, types):
    T = np.asarray(T_44, dtype=np.float64)
    q = matrix_to_quat(T[:3, :3])
    return types('geometry_msgs/msg/Pose',
                 position=types('geometry_msgs/msg/Point', x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
                 orientation=types('geometry_msgs/msg/Quaternion', x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                   w=float(q[3])))


def matrix_to_pose_stamped(T_44, header, frame_id: str | None = None, types: MessageTypes = ROS):
    return types('geometry_msgs/msg/PoseStamped', header=header_for(header, frame_id, types),
                 pose=_pose_msg(T_44, types))


def matrix_to_odometry(T_world_base_44, header, child_frame_id: str, frame_id: str | None = None,
                       types: MessageTypes = ROS, position_sigma: float = 0.0, rotation_sigma: float = 0.0,
                       pose_covariance_66=None, twist_covariance_66=None):
    """4x4 T_world_base -> nav_msgs/Odometry (zero twist; diagonal pose covariance from the sigmas, or
    ``pose_covariance_66`` as given; twist covariance ``twist_covariance_66``, else zeros)."""
    cov = np.zeros((6, 6))
    cov[[0, 1, 2], [0, 1, 2]] = position_sigma ** 2
    cov[[3, 4, 5], [3, 4, 5]] = rotation_sigma ** 2
    if pose_covariance_66 is not None:
        cov = np.asarray(pose_covariance_66, np.float64).reshape(6, 6)
    twist_cov = np.zeros(36) if twist_covariance_66 is None else np.asarray(twist_covariance_66, np.float64)
    vec = lambda: types('geometry_msgs/msg/Vector3', x=0.0, y=0.0, z=0.0)  # noqa: E731
    return types('nav_msgs/msg/Odometry', header=header_for(header, frame_id, types),
                 child_frame_id=str(child_frame_id),
                 pose=types('geometry_msgs/msg/PoseWithCovariance', pose=_pose_msg(T_world_base_44, types),
                            covariance=f64_values(cov, 36)),
                 twist=types('geometry_msgs/msg/TwistWithCovariance',
                             twist=types('geometry_msgs/msg/Twist', linear=vec(), angular=vec()),
                             covariance=f64_values(twist_cov, 36)))
