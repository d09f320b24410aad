"""What goes into and comes out of the streaming estimator (plain numpy; no ROS, no torch)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Frame:
    """One camera image with its intrinsics and (when known) its pose.

    image: uint8 HxWx3 RGB. K_33: intrinsics of this image size. T_world_cam_44: camera-to-world pose
    (OpenCV axes), or None when no pose source is available (odometry-free mode). stamp: seconds.
    """
    stamp: float
    image: np.ndarray
    K_33: np.ndarray
    T_world_cam_44: np.ndarray | None = None
    frame_id: str = 'camera'


@dataclass
class DepthOutput:
    """Depth and confidence for one input frame, at the size the caller asked for.

    depth_hw: float32 metres, NaN where there is no estimate. confidence_hw: float32 in [0, 1], higher is
    more certain (NaN-free; 0 where there is no estimate). K_33: intrinsics of the output size.
    """
    stamp: float
    depth_hw: np.ndarray
    confidence_hw: np.ndarray
    K_33: np.ndarray
    is_keyframe: bool
    T_world_cam_44: np.ndarray | None = None   # the pose used (refined when pose refinement is on)
    reset_reason: str | None = None            # why the filter restarted at this frame, if it did
    timings_ms: dict = field(default_factory=dict)
