"""The stream-continuity rules, each written once (no ROS, no torch).

Rules between two consecutive frames of one camera stream:

* time order (:func:`time_order`): a stamp equal to the previous one is a *duplicate* (the frame is dropped);
  a smaller one means time went *backwards* (a bag restarting, a simulator reset: everything restarts);
* size (:func:`size_change`): another image size restarts the stream;
* intrinsics, time gap and camera jump (:func:`stream_break`, which applies all rules for a posed frame):
  the time gap is the camera stream's own (``sensor_gap_s`` when the caller gives it, else the time since the
  previous frame), and a jump is judged against the elapsed time (``jump_limit``): more than ``reset_translation``
  m / ``reset_rotation_deg`` degrees per second, never less than those values. A threshold of 0 disables a rule.

The estimator applies :func:`stream_break` to every pushed frame (its resets); the node applies :func:`time_order`
and :func:`size_change` to each received image before it looks up the image's pose (a stream that went backwards
also restarts the odometry buffer). Odometry teleports are the pose buffer's rule (``pose_buffer``).
"""
from __future__ import annotations

from typing import Optional, Tuple

import numpy as np

from .filter import jump_limit
from .geometry import pose_delta_np

__all__ = ['jump_limit', 'time_order', 'size_change', 'stream_break', 'BACKWARDS', 'DUPLICATE']

BACKWARDS = 'backwards'
DUPLICATE = 'duplicate'


def time_order(previous: Optional[float], stamp: float) -> Optional[str]:
    """None when ``stamp`` follows ``previous`` (or there is none), else :data:`DUPLICATE` or :data:`BACKWARDS`."""
    if previous is None:
        return None
    if stamp == previous:
        return DUPLICATE
    if stamp < previous:
        return BACKWARDS
    return None


def backwards_reason(previous: float, stamp: float, digits: int = 6) -> str:
    return f'time went backwards ({stamp:.{digits}f} s after {previous:.{digits}f} s)'


def size_change(previous: Optional[Tuple[int, int]], size: Tuple[int, int]) -> Optional[str]:
    """The reason when the image size (w, h) changed, else None."""
    if previous is None or tuple(previous) == tuple(size):
        return None
    return f'image size changed from {previous[0]}x{previous[1]} to {size[0]}x{size[1]}'


def stream_break(last, stamp: float, T: np.ndarray, size, K_in, sensor_gap_s: Optional[float], *,
                 reset_time_gap: float, reset_translation: float, reset_rotation_deg: float) -> Optional[str]:
    """Why the stream must restart at this frame, or None. ``last``: (stamp, T_world_cam, size, K) of the previous
    accepted frame, or None. Duplicates are the caller's (:func:`time_order`) and never reach here."""
    if last is None:
        return None
    last_stamp, last_T, last_size, last_K = last
    if time_order(last_stamp, stamp) == BACKWARDS:
        return backwards_reason(last_stamp, stamp)
    changed = size_change(last_size, size)
    if changed is not None:
        return changed
    if not np.allclose(K_in, last_K, rtol=1e-6, atol=1e-6):
        return 'camera intrinsics changed'
    elapsed = stamp - last_stamp
    if sensor_gap_s is not None:
        gap, where = float(sensor_gap_s), 'in the camera stream'
    else:
        gap, where = elapsed, 'since the previous frame'
    if reset_time_gap > 0 and gap > reset_time_gap:
        return f'time gap {gap:.3f} s {where} > reset_time_gap {reset_time_gap:g} s'
    dt, dr = pose_delta_np(last_T, T)
    lim_t = jump_limit(reset_translation, elapsed)
    lim_r = jump_limit(reset_rotation_deg, elapsed)
    if reset_translation > 0 and dt > lim_t:
        return (f'camera jumped {dt:.3f} m in {elapsed:.3f} s > {lim_t:.3f} m '
                f'(reset_translation {reset_translation:g} m per second, at least that)')
    if reset_rotation_deg > 0 and dr > lim_r:
        return (f'camera turned {dr:.1f} deg in {elapsed:.3f} s > {lim_r:.1f} deg '
                f'(reset_rotation_deg {reset_rotation_deg:g} deg per second, at least that)')
    return None
