"""The stream-continuity rules, each written once (no ROS, no torch).

Rules between two consecutive frames of one camera stream:

* time order (:func:`time_order`): a stamp equal to the previous one is a *duplicate* (the frame is dropped);
  a smaller one means time went *backwards* (a bag restarting, a simulator reset: everything restarts);
* size (:func:`size_change`): another image size restarts the stream; a caller that receives images (the node)
  first applies :class:`StreamSize`: the stream takes a new size only once it persists (``size_change_images`` images
  in a row of it), and an image of another size before that is a *stray* (dropped, never restarting anything);
* time from the future (:func:`future_stamp`): an image stamped ahead of both the receiver's clock and the newest
  odometry by more than a tolerance cannot get a pose by waiting (the clocks disagree or the stamp is wrong);
* intrinsics, time gap and teleport (:func:`stream_break`, which applies all rules for a posed frame):
  the time gap is the camera stream's own (``sensor_gap_s`` when the caller gives it, else the time since the
  previous frame; frames a busy caller left out do not make a gap), and a *teleport* (:func:`teleport`) is a pose
  step no camera can make in the elapsed time: faster than ``odom_max_speed`` m/s and over
  :data:`TELEPORT_FLOOR_M`, or turning faster than ``odom_max_rate_deg`` deg/s and over
  :data:`TELEPORT_FLOOR_DEG`. A threshold of 0 disables a rule.

Fast but smooth motion is no discontinuity: a 90 deg/s pan or a 1.5 m/s walk, with frames pushed a second apart,
never resets (the filter's predict step warps the belief across any motion); a 0.5 m step between two frames
1/30 s apart (15 m/s) does.

One teleport rule for both places that see poses: the pose buffer (``pose_buffer``) applies :func:`teleport` to
consecutive odometry messages, the estimator to consecutive pushed frames (offline, where poses come without a
buffer). The estimator applies :func:`stream_break` to every pushed frame (its resets). A caller that looks poses
up in a ``PoseBuffer`` (the node) applies :func:`time_order` and :func:`size_change` to each received image before
the lookup, and the teleports the buffer found to the poses it gets, through :class:`ReceivedImages` (a stream that
went backwards also restarts the odometry buffer).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np

from dpv_sensor.core.pose_math import pose_delta_np

__all__ = ['teleport', 'time_order', 'size_change', 'stream_break', 'ReceivedImages', 'ImageVerdict', 'BACKWARDS',
           'DUPLICATE', 'TELEPORT_FLOOR_M', 'TELEPORT_FLOOR_DEG', 'StreamSize', 'SizeVerdict', 'future_stamp']

# A pose step is only a teleport when it is also larger than these (jitter of fast odometry is not one).
TELEPORT_FLOOR_M = 0.1
TELEPORT_FLOOR_DEG = 10.0

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


@dataclass(frozen=True)
class SizeVerdict:
    """What :class:`StreamSize` says about an image's size: taken (``stray`` None; ``changed``: the stream's size
    became this one with it, ``previous`` the size before), or a stray of another size (``stray``: why; the image is
    dropped)."""
    stray: Optional[str] = None
    changed: bool = False
    previous: Optional[Tuple[int, int]] = None

    @property
    def taken(self) -> bool:
        return self.stray is None


class StreamSize:
    """The image size of a received stream, which changes only when a new size persists.

    The stream's size is its first image's. An image of another size is a *stray* (a glitching driver, a thumbnail or
    a full-resolution still on the video topic) until ``persist_images`` images in a row have that one new size: the
    last of them is taken, and the stream's size is the new one from then on (the caller restarts the filter once, at
    it, as for any size change). An image of the stream's size ends a run; an image of a third size starts its own.
    ``persist_images`` 1 takes every new size at once. Only the images the caller hands in count (one it refused for
    another reason, e.g. too small to use, is neither in a run nor ends one)."""

    def __init__(self, persist_images: int):
        if int(persist_images) < 1:
            raise ValueError(f'persist_images must be at least 1, got {persist_images}')
        self.persist_images = int(persist_images)
        self.size: Optional[Tuple[int, int]] = None
        self._candidate: Optional[Tuple[int, int]] = None
        self._run = 0

    def image(self, size: Tuple[int, int]) -> SizeVerdict:
        """The verdict on an image of ``size`` (w, h)."""
        size = (int(size[0]), int(size[1]))
        if self.size is None or size == self.size:
            self.size = size
            self._candidate, self._run = None, 0
            return SizeVerdict()
        if size == self._candidate:
            self._run += 1
        else:
            self._candidate, self._run = size, 1
        if self._run >= self.persist_images:
            previous, self.size = self.size, size
            self._candidate, self._run = None, 0
            return SizeVerdict(changed=True, previous=previous)
        (w, h), (w0, h0) = size, self.size
        return SizeVerdict(stray=f"{w}x{h} is not the stream's {w0}x{h0} ({self._run} image(s) in a row of "
                                 f'{w}x{h}; a new size is taken once {self.persist_images} in a row have it)')


def future_stamp(stamp_ns: int, clock_ns: int, newest_odometry_ns: Optional[int], tolerance_s: float) -> Optional[str]:
    """Why an image stamped ``stamp_ns`` comes from the future: ahead of the receiver's clock ``clock_ns`` and of the
    newest odometry stamp ``newest_odometry_ns`` (None: no odometry yet, every stamp is ahead of it) each by more than
    ``tolerance_s`` seconds; else None. A clock that reads 0 or less (sim time before the first /clock) says
    nothing: None."""
    if clock_ns <= 0:
        return None
    tolerance_ns = float(tolerance_s) * 1e9
    ahead_clock = int(stamp_ns) - int(clock_ns)
    if ahead_clock <= tolerance_ns:
        return None
    odometry = 'no odometry has arrived yet'
    if newest_odometry_ns is not None:
        ahead_odometry = int(stamp_ns) - int(newest_odometry_ns)
        if ahead_odometry <= tolerance_ns:
            return None
        odometry = f'{ahead_odometry / 1e9:.3f} s ahead of the newest odometry'
    return f"stamped {ahead_clock / 1e9:.3f} s ahead of the node's clock, {odometry}"


def teleport(elapsed_s: float, distance_m: float, angle_deg: float, max_speed: float,
             max_rate_deg: float) -> Optional[str]:
    """Why a pose step of ``distance_m`` metres and ``angle_deg`` degrees in ``elapsed_s`` seconds is a teleport
    (faster than ``max_speed`` m/s and over :data:`TELEPORT_FLOOR_M`, or faster than ``max_rate_deg`` deg/s and
    over :data:`TELEPORT_FLOOR_DEG`), or None. A limit of 0 disables that half of the rule."""
    dt = max(float(elapsed_s), 0.0)
    if max_speed > 0 and distance_m > max(max_speed * dt, TELEPORT_FLOOR_M):
        return (f'{distance_m:.3f} m in {dt:.3f} s ({distance_m / max(dt, 1e-9):.1f} m/s > '
                f'odom_max_speed {max_speed:g} m/s)')
    if max_rate_deg > 0 and angle_deg > max(max_rate_deg * dt, TELEPORT_FLOOR_DEG):
        return (f'{angle_deg:.1f} deg in {dt:.3f} s ({angle_deg / max(dt, 1e-9):.0f} deg/s > '
                f'odom_max_rate_deg {max_rate_deg:g} deg/s)')
    return None


def stream_break(last, stamp: float, T: np.ndarray, size, K_in, sensor_gap_s: Optional[float], *,
                 reset_time_gap: float, max_speed: float, max_rate_deg: float) -> Optional[str]:
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
    jump = teleport(elapsed, dt, dr, max_speed, max_rate_deg)
    return None if jump is None else f'pose teleported: {jump}'



@dataclass(frozen=True)
class ImageVerdict:
    """What the rules say about a received image (:meth:`ReceivedImages.image`): drop it (a duplicate stamp), or
    restart the stream before it: time went backwards (``backwards``: the reason; ``previous_ns``: the stamp before;
    ``poses_cleared``: the odometry had not gone back yet, so its samples were cleared) and / or the image size
    changed (``size_change``: the reason; ``previous_size``: (w, h) before)."""
    duplicate: bool = False
    backwards: Optional[str] = None
    previous_ns: Optional[int] = None
    poses_cleared: bool = False
    size_change: Optional[str] = None
    previous_size: Optional[Tuple[int, int]] = None


class ReceivedImages:
    """The rules on the images a caller receives, before it looks their pose up in ``pose_buffer`` (a
    ``PoseBuffer``): :func:`time_order` (a stream that went backwards clears the buffer unless the odometry went
    back too) and :func:`size_change`; and :meth:`pose_teleported`: a pose from after an odometry teleport the
    buffer found. The caller restarts its pipeline where they say so."""

    def __init__(self, pose_buffer):
        self.pose_buffer = pose_buffer
        self._last_stamp_ns: Optional[int] = None
        self._last_size: Optional[Tuple[int, int]] = None
        self._last_epoch = pose_buffer.epoch
        self._last_jumps = pose_buffer.jumps

    def image(self, stamp_ns: int, size: Tuple[int, int]) -> ImageVerdict:
        """The verdict on the image at ``stamp_ns`` of ``size`` (w, h); a duplicate leaves the state untouched."""
        last_ns, last_size = self._last_stamp_ns, self._last_size
        order = time_order(last_ns, stamp_ns)
        if order == DUPLICATE:
            return ImageVerdict(duplicate=True)
        backwards, cleared = None, False
        if order == BACKWARDS:
            backwards = backwards_reason(last_ns / 1_000_000_000, stamp_ns / 1_000_000_000, digits=3)
            cleared = self.pose_buffer.epoch == self._last_epoch   # the odometry has not jumped back (yet)
            if cleared:
                self.pose_buffer.clear('image time went backwards')
            last_size = None
        self._last_stamp_ns = stamp_ns
        self._last_epoch = self.pose_buffer.epoch
        self._last_size = tuple(size)
        changed = size_change(last_size, size)
        return ImageVerdict(backwards=backwards, previous_ns=last_ns if backwards else None, poses_cleared=cleared,
                            size_change=changed, previous_size=last_size if changed else None)

    def pose_teleported(self) -> bool:
        """True once for a pose looked up after an odometry teleport the buffer found since the last one: the
        pipeline's belief is in the old frame."""
        if self.pose_buffer.jumps == self._last_jumps:
            return False
        self._last_jumps = self.pose_buffer.jumps
        return True
