"""What goes into and comes out of the streaming estimator (plain numpy; no ROS, no torch)."""
from __future__ import annotations

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
