"""Odometry buffer: the camera pose at an image stamp, interpolated between odometry messages (numpy, no ROS).

The node pushes every odometry message into a `PoseBuffer` (`add(stamp_ns, T_world_base_44)`) and asks for
the camera pose at each image stamp (`pose_at(stamp_ns)`). The answer is interpolated between the two
messages that bracket the stamp — SLERP for the rotation, linear for the translation — and composed with the
static `T_base_camera` so the caller gets `T_world_cam`. When no pose can be given, the answer says why:

  'future'   no odometry at or after the stamp yet (the caller may wait for it, up to odom_wait_timeout)
  'too old'  the stamp is before the oldest message still held
  'gap'      the two bracketing messages are further apart than max_gap seconds
  'nan'      one of the bracketing messages was invalid (NaN / non-unit quaternion)

Stamps are integer nanoseconds (exactly what ROS headers carry) so no precision is lost. A message older
than the newest one by more than `backwards_tolerance_s` means time went backwards (a bag restarting, a
simulator reset): the buffer clears itself, counts it in `epoch` and reports it from `add`.

A message that moves further from the previous one than a camera can move in between (an odometry *teleport*:
a relocalisation, a loop-closure correction in a map frame, a driver restart at another pose) cannot be
interpolated across: with `max_speed` / `max_rate_deg` set, a step of more than `max_speed * dt` metres or
`max_rate_deg * dt` degrees (and at least `JUMP_FLOOR_M` / `JUMP_FLOOR_DEG`, so jitter of fast odometry is not
flagged; the rule is ``continuity.teleport``, the same the estimator applies to offline pose steps)
clears the older samples, counts it in `jumps` and is reported from `add`. Images before it then get
'too old'; the caller should restart whatever it accumulated in the old pose frame.

Two messages with the same stamp are one sample: an identical repeat (within `SAME_POSE_M` / `SAME_POSE_DEG`; a
republished or re-bridged message) is ignored and counted in `duplicates`; one with another pose is a *conflict*
(two odometry sources on one topic, a driver bug): the first message is kept, it is counted in `conflicts` and
`last_conflict` says what differed, so the caller can warn. Which of two such poses is right cannot be known, and
keeping the first keeps every pose already handed out consistent.

Quaternions in this module are ROS order (x, y, z, w).
"""
from __future__ import annotations

import bisect
import threading
from dataclasses import dataclass

import numpy as np

# the pose maths has one home, pose_math.py; these names are this module's vocabulary (bag I/O, the node)
from dpv_sensor.stream.continuity import TELEPORT_FLOOR_DEG, TELEPORT_FLOOR_M, teleport
from dpv_sensor.core.pose_math import interpolate_pose, make_pose, matrix_to_quat, quat_angle_deg, quat_to_matrix, slerp  # noqa: F401

NS = 1_000_000_000

# A step between consecutive odometry samples is only a teleport when it is also larger than these.
JUMP_FLOOR_M = TELEPORT_FLOOR_M
JUMP_FLOOR_DEG = TELEPORT_FLOOR_DEG

# Two samples at one stamp are the same pose when they differ by at most this much (float round trips, re-bridged
# messages); more is a conflict.
SAME_POSE_M = 1e-4
SAME_POSE_DEG = 0.01

# Reasons pose_at() gives when it cannot answer.
FUTURE = 'future'
TOO_OLD = 'too old'
GAP = 'gap'
NAN = 'nan'


# --------------------------------------------------------------------------------------------------------------
# quaternion / SE(3) helpers (float64 numpy)
# --------------------------------------------------------------------------------------------------------------
def pose7_to_matrix(pose7) -> np.ndarray:
    """[x, y, z, qx, qy, qz, qw] (the T_base_camera parameter form) -> 4x4."""
    p = [float(v) for v in pose7]
    if len(p) != 7:
        raise ValueError(f'expected [x, y, z, qx, qy, qz, qw], got {len(p)} numbers')
    return make_pose(p[:3], p[3:])


def matrix_to_pose7(T_44) -> list[float]:
    """4x4 -> [x, y, z, qx, qy, qz, qw]."""
    T = np.asarray(T_44, dtype=np.float64)
    return [*map(float, T[:3, 3]), *map(float, matrix_to_quat(T[:3, :3]))]


def is_valid_pose(T_44) -> bool:
    """Finite 4x4 whose rotation block is orthonormal (to 1e-3) with determinant +1."""
    if T_44 is None:
        return False
    T = np.asarray(T_44, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return False
    R = T[:3, :3]
    return bool(np.allclose(R @ R.T, np.eye(3), atol=1e-3) and np.linalg.det(R) > 0.0)


# --------------------------------------------------------------------------------------------------------------
# the buffer
# --------------------------------------------------------------------------------------------------------------
@dataclass
class PoseQuery:
    """Answer of PoseBuffer.pose_at: a pose, or None with a reason (one of FUTURE, TOO_OLD, GAP, NAN)."""
    T_world_cam_44: np.ndarray | None
    reason: str | None = None
    detail: str = ''

    @property
    def ok(self) -> bool:
        return self.T_world_cam_44 is not None


class PoseBuffer:
    """Time-ordered odometry samples; interpolated camera poses at arbitrary stamps. Thread-safe.

    max_gap_s: largest bracket an image pose is interpolated across. history_s: samples older than this
    behind the newest are discarded (memory stays flat). T_base_camera_44: static camera pose in the odometry
    child frame (identity when None). backwards_tolerance_s: out-of-order arrivals within this window are
    inserted in order instead of clearing the buffer (0: any step back clears it).
    """

    def __init__(self, max_gap_s: float = 0.5, history_s: float = 30.0, T_base_camera_44=None,
                 backwards_tolerance_s: float = 0.0, max_samples: int = 100_000, max_speed: float = 0.0,
                 max_rate_deg: float = 0.0):
        self.max_gap_ns = int(round(max_gap_s * NS))
        self.history_ns = int(round(history_s * NS))
        self.backwards_tolerance_ns = int(round(backwards_tolerance_s * NS))
        self.max_samples = int(max_samples)
        self.T_base_camera = np.eye(4) if T_base_camera_44 is None else np.asarray(T_base_camera_44, np.float64)
        self._stamps: list[int] = []
        self._t: list[np.ndarray | None] = []   # translation, None for an invalid sample
        self._q: list[np.ndarray | None] = []   # quaternion (x, y, z, w)
        self._lock = threading.Lock()
        self.max_speed = float(max_speed)          # m/s; 0 = no teleport check on translation
        self.max_rate_deg = float(max_rate_deg)    # deg/s; 0 = no teleport check on rotation
        self.epoch = 0            # how many times time went backwards (and the buffer cleared itself)
        self.jumps = 0            # how many odometry teleports cleared the buffer
        self.conflicts = 0        # messages at a stamp already held with another pose (ignored: the first is kept)
        self.duplicates = 0       # messages at a stamp already held with the same pose (ignored)
        self.last_conflict: str | None = None
        self.cleared_reason: str | None = None

    # ---- state -------------------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self._stamps)

    @property
    def newest_ns(self) -> int | None:
        with self._lock:
            return self._stamps[-1] if self._stamps else None

    @property
    def oldest_ns(self) -> int | None:
        with self._lock:
            return self._stamps[0] if self._stamps else None

    def clear(self, reason: str | None = None) -> None:
        with self._lock:
            self._clear(reason)

    def _clear(self, reason):
        self._stamps.clear()
        self._t.clear()
        self._q.clear()
        self.cleared_reason = reason

    # ---- input -------------------------------------------------------------------------------------------
    def add(self, stamp_ns: int, T_world_base_44) -> str | None:
        """Insert one odometry sample. `T_world_base_44` None or non-finite/non-rigid marks an invalid sample
        (images bracketed by it get reason 'nan'). Returns a message when the buffer cleared itself because
        time went backwards or the odometry teleported (see the module doc), else None."""
        stamp_ns = int(stamp_ns)
        if is_valid_pose(T_world_base_44):
            T = np.asarray(T_world_base_44, dtype=np.float64)
            t, q = T[:3, 3].copy(), matrix_to_quat(T[:3, :3])
        else:
            t = q = None
        cleared = None
        with self._lock:
            if self._stamps and stamp_ns < self._stamps[-1] - self.backwards_tolerance_ns:
                cleared = (f'odometry time went backwards by {(self._stamps[-1] - stamp_ns) / NS:.3f} s '
                           f'({self._stamps[-1] / NS:.3f} -> {stamp_ns / NS:.3f}); pose buffer cleared')
                self._clear(cleared)
                self.epoch += 1
            i = bisect.bisect_left(self._stamps, stamp_ns)
            if i < len(self._stamps) and self._stamps[i] == stamp_ns:   # same stamp again: the first is kept
                differs = self._difference(self._t[i], self._q[i], t, q)
                if differs is None:
                    self.duplicates += 1
                else:
                    self.conflicts += 1
                    self.last_conflict = f'conflicting odometry at {stamp_ns / NS:.3f} s: {differs}'
                return None
            if t is not None and self._stamps and stamp_ns > self._stamps[-1] and self._t[-1] is not None:
                jump = self._jump(stamp_ns, t, q)
                if jump:
                    cleared = f'odometry jumped {jump}; pose buffer cleared'
                    self._clear(cleared)
                    self.jumps += 1
            i = bisect.bisect_left(self._stamps, stamp_ns)
            self._stamps.insert(i, stamp_ns)
            self._t.insert(i, t)
            self._q.insert(i, q)
            self._trim()
        return cleared

    @staticmethod
    def _difference(t0, q0, t1, q1) -> str | None:
        """How two samples at one stamp differ ('0.050 m and 0.0 deg apart', 'one is invalid'), or None when they
        are the same pose (see SAME_POSE_M / SAME_POSE_DEG)."""
        if t0 is None or t1 is None:
            return None if t0 is None and t1 is None else 'one of the two is invalid (NaN or non-unit quaternion)'
        dist = float(np.linalg.norm(t1 - t0))
        angle = quat_angle_deg(q0, q1)
        if dist <= SAME_POSE_M and angle <= SAME_POSE_DEG:
            return None
        return f'two poses {dist:.3f} m and {angle:.1f} deg apart'

    def _jump(self, stamp_ns: int, t: np.ndarray, q: np.ndarray) -> str | None:
        """Why the step from the newest sample to (t, q) at stamp_ns is a teleport, or None."""
        dt = (stamp_ns - self._stamps[-1]) / NS
        dist = float(np.linalg.norm(t - self._t[-1]))
        angle = quat_angle_deg(q, self._q[-1])
        why = teleport(dt, dist, angle, self.max_speed, self.max_rate_deg)
        return None if why is None else f'{why} at {stamp_ns / NS:.3f} s'


    def _trim(self):
        newest = self._stamps[-1]
        cut = bisect.bisect_left(self._stamps, newest - self.history_ns)
        cut = max(cut, len(self._stamps) - self.max_samples)
        # keep one sample before the horizon so stamps just inside it can still be bracketed
        cut = max(0, cut - 1)
        if cut:
            del self._stamps[:cut], self._t[:cut], self._q[:cut]

    def discard_newer_than(self, stamp_ns: int) -> int:
        """Drop samples stamped after `stamp_ns` (used when images jump back in time before odometry does).
        Returns how many were dropped."""
        with self._lock:
            i = bisect.bisect_right(self._stamps, int(stamp_ns))
            n = len(self._stamps) - i
            del self._stamps[i:], self._t[i:], self._q[i:]
            return n

    # ---- queries -----------------------------------------------------------------------------------------
    def base_pose_at(self, stamp_ns: int) -> PoseQuery:
        """T_world_base at `stamp_ns` (see pose_at)."""
        stamp_ns = int(stamp_ns)
        with self._lock:
            stamps = self._stamps
            if not stamps or stamp_ns > stamps[-1]:
                newest = f'newest odometry {stamps[-1] / NS:.3f}' if stamps else 'no odometry yet'
                return PoseQuery(None, FUTURE, f'image {stamp_ns / NS:.3f} s, {newest}')
            if stamp_ns < stamps[0]:
                return PoseQuery(None, TOO_OLD, f'image {stamp_ns / NS:.3f} s is before the oldest odometry '
                                 f'{stamps[0] / NS:.3f} s')
            i = bisect.bisect_left(stamps, stamp_ns)
            if stamps[i] == stamp_ns:
                j0 = j1 = i
            else:
                j0, j1 = i - 1, i
            t0, t1 = stamps[j0], stamps[j1]
            if self._t[j0] is None or self._t[j1] is None:
                bad = t0 if self._t[j0] is None else t1
                return PoseQuery(None, NAN, f'odometry at {bad / NS:.3f} s is invalid (NaN or non-unit quaternion)')
            if t1 - t0 > self.max_gap_ns:
                return PoseQuery(None, GAP, f'odometry gap {(t1 - t0) / NS:.3f} s around image '
                                 f'{stamp_ns / NS:.3f} s exceeds max_odom_gap {self.max_gap_ns / NS:.3f} s')
            if j0 == j1:
                return PoseQuery(make_pose(self._t[j0], self._q[j0]))
            alpha = (stamp_ns - t0) / (t1 - t0)
            q = slerp(self._q[j0], self._q[j1], alpha)
            t = self._t[j0] + alpha * (self._t[j1] - self._t[j0])
            return PoseQuery(make_pose(t, q))

    def pose_at(self, stamp_ns: int, T_base_camera_44=None) -> PoseQuery:
        """T_world_cam = T_world_base(stamp) @ T_base_camera, or None with the reason it cannot be given.
        `T_base_camera_44`: the camera mount for this image (a mount from TF), instead of the buffer's own."""
        q = self.base_pose_at(stamp_ns)
        if q.ok:
            mount = self.T_base_camera if T_base_camera_44 is None else np.asarray(T_base_camera_44, np.float64)
            q.T_world_cam_44 = q.T_world_cam_44 @ mount
        return q


class CovarianceTrack:
    """The odometry's pose covariance over time (6x6 per sample, None where the publisher leaves it unfilled),
    linearly interpolated at an image stamp; the newest ``max_samples`` are kept. Thread-safe."""

    def __init__(self, max_samples: int = 2000):
        self.max_samples = int(max_samples)
        self._stamps: list[int] = []
        self._cov: list[np.ndarray | None] = []
        self._lock = threading.Lock()

    def add(self, stamp_ns: int, cov_66) -> None:
        with self._lock:
            if self._stamps and int(stamp_ns) < self._stamps[-1]:
                self._stamps.clear()
                self._cov.clear()
            self._stamps.append(int(stamp_ns))
            self._cov.append(None if cov_66 is None else np.asarray(cov_66, np.float64).reshape(6, 6))
            if len(self._stamps) > self.max_samples:
                del self._stamps[0], self._cov[0]

    def at(self, stamp_ns: int) -> np.ndarray | None:
        """The covariance at ``stamp_ns`` (interpolated between the samples around it, the nearest at the ends);
        None without samples or where one of them is unfilled."""
        with self._lock:
            if not self._stamps:
                return None
            i = bisect.bisect_left(self._stamps, int(stamp_ns))
            if i <= 0 or i >= len(self._stamps):
                c = self._cov[0 if i <= 0 else -1]
                return None if c is None else c.copy()
            c0, c1 = self._cov[i - 1], self._cov[i]
            if c0 is None or c1 is None:
                return None
            t0, t1 = self._stamps[i - 1], self._stamps[i]
            a = (int(stamp_ns) - t0) / (t1 - t0) if t1 > t0 else 1.0
            return (1.0 - a) * c0 + a * c1
