"""What goes into and comes out of the streaming estimator, and what a frame must be to go in (plain numpy; no ROS,
no torch)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

# The smallest image side (pixels) the estimator takes: one pixel has no neighbour to resize, grade or match with.
# The estimator refuses a smaller Frame.image (ValueError); the node refuses such images on receipt.
MIN_IMAGE_SIDE = 2


def image_too_small(width: int, height: int) -> str | None:
    """Why a width x height image is too small for the estimator (a side under :data:`MIN_IMAGE_SIDE`), or None."""
    if min(int(width), int(height)) >= MIN_IMAGE_SIDE:
        return None
    return (f'{int(width)}x{int(height)} is smaller than the smallest image the estimator takes '
            f'({MIN_IMAGE_SIDE}x{MIN_IMAGE_SIDE} pixels)')


@dataclass
class Frame:
    """One camera image with its intrinsics and (when known) its pose.

    image: uint8 HxWx3 RGB. K_33: intrinsics of this image size. T_world_cam_44: camera-to-world pose
    (OpenCV axes), or None when no pose source is available (odometry-free mode). stamp: seconds.

    sensor_gap_s: what the camera stream did since the previous frame the caller *pushed*: the longest
    interval (s) between consecutive images the caller *received* in that time, whether it passed them on
    or dropped them (e.g. the node's newest-wins mailbox while the estimator was busy). With no image
    dropped in between it is simply ``stamp`` minus the previous image's stamp. The estimator's time-gap
    reset (``reset_time_gap``) judges this value, so deliberate drops do not restart the filter while a
    camera stream that really stalled still does. None (offline use, replaying every frame): unknown; the
    estimator then uses the time since the previous pushed frame.

    pose_covariance_66: covariance of the camera pose from the odometry (6x6, ROS order: x, y, z, rotation about
    x, y, z), None when the odometry does not fill it; twist_covariance_66: the odometry's twist covariance (6x6,
    ROS order, in its child frame, read as the variance the relative pose gains per second:
    ``dpv_sensor.core.odometry_covariance``), None when not filled. They set the pose uncertainty of the measurement
    and the window's odometry factors (``pose_uncertainty``, docs/pose_uncertainty.md).
    """
    stamp: float
    image: np.ndarray
    K_33: np.ndarray
    T_world_cam_44: np.ndarray | None = None
    frame_id: str = 'camera'
    sensor_gap_s: float | None = None
    pose_covariance_66: np.ndarray | None = None
    twist_covariance_66: np.ndarray | None = None


@dataclass
class DepthOutput:
    """Depth and confidence for one input frame, at the size the caller asked for.

    depth_hw: float32 metres, NaN where there is no estimate. confidence_hw: float32 in [0, 1], higher is
    more certain (NaN-free; 0 where there is no estimate). K_33: intrinsics of the output size.
    timings_ms: wall time (ms) of the push that made it, by stage ('resize', 'pose_refinement', 'measurement',
    'pose_uncertainty', 'filter', 'refine' or 'upsample', 'output'; 'between' for a non-keyframe) and 'total';
    a key 'stage.part' is a part of that stage, already counted in it (e.g. 'measurement.features',
    'filter.knet', 'refine.rnet', 'refine.edge_filter', 'pose_refinement.keypoints').
    """
    stamp: float
    depth_hw: np.ndarray
    confidence_hw: np.ndarray
    K_33: np.ndarray
    is_keyframe: bool
    T_world_cam_44: np.ndarray | None = None   # the pose used (refined when pose refinement is on)
    reset_reason: str | None = None            # why the filter restarted at this frame, if it did
    timings_ms: dict = field(default_factory=dict)
    features: dict | None = None               # keyframe confidence cues by name (Estimator.collect_features)
    anchors: object | None = None              # the keyframe's metric anchors report (stream.metric_anchors)


def checked_image(frame: Frame) -> np.ndarray:
    """The frame's image, or ValueError saying what is wrong with the frame's image or ``sensor_gap_s`` (a
    caller's error: the estimator refuses the frame)."""
    image = np.asarray(frame.image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f'Frame.image must be uint8 HxWx3 RGB, got {image.dtype} {image.shape}')
    small = image_too_small(image.shape[1], image.shape[0])
    if small is not None:
        raise ValueError(f'Frame.image is too small: {small}')
    gap = frame.sensor_gap_s
    if gap is not None and not (math.isfinite(float(gap)) and float(gap) >= 0.0):
        raise ValueError(f'Frame.sensor_gap_s must be None or a finite number >= 0, got {gap!r}')
    return image


def drop_reason(frame: Frame) -> str | None:
    """Why the estimator drops the frame (its pose, intrinsics or stamp unusable), or None."""
    if frame.T_world_cam_44 is None:
        return 'no pose for the frame'
    T = np.asarray(frame.T_world_cam_44, dtype=np.float64)
    if T.shape != (4, 4):
        return f'pose has shape {T.shape}, expected 4x4'
    if not np.all(np.isfinite(T)):
        return 'pose is not finite (NaN/inf)'
    if not is_rigid(T):
        return 'pose is not a rigid transform'
    K = np.asarray(frame.K_33, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        return 'invalid intrinsics K'
    if not math.isfinite(float(frame.stamp)):
        return 'stamp is not finite'
    return None


def is_rigid(T_44: np.ndarray, tol: float = 1e-3) -> bool:
    """A 4x4 pose whose rotation is orthonormal with determinant 1 and whose last row is [0, 0, 0, 1]."""
    R = T_44[:3, :3]
    return (np.allclose(R.T @ R, np.eye(3), atol=tol) and abs(np.linalg.det(R) - 1.0) < tol
            and np.allclose(T_44[3], [0.0, 0.0, 0.0, 1.0], atol=tol))
