"""Keyframe selection and the sliding window of keyframes (numpy + torch tensors; no ROS).

:class:`KeyframeSelector` decides, frame by frame, whether a frame becomes a keyframe:

- the first frame after construction or :meth:`KeyframeSelector.reset` is always a keyframe;
- otherwise a frame is a keyframe when, relative to the **last keyframe**, the camera has moved at
  least ``translation`` metres (baseline), or turned at least ``rotation_deg`` degrees, or when
  ``max_interval`` frames have passed since it (the frame-count fallback; the paper takes every 5th
  frame, ``delta t = 5``). A threshold of 0 disables that criterion (``translation = rotation_deg = 0``
  and ``max_interval = 5`` is exactly the paper's fixed spacing; ``max_interval = 1`` makes every frame
  a keyframe).

:class:`KeyframeWindow` keeps the last ``capacity`` keyframes (default 5, the paper's window) and picks
the reference and source keyframes of a plane sweep:

- ``causal``: the reference is the newest keyframe, the sources are the keyframes before it (up to
  ``capacity - 1``). Needs at least 2 keyframes (with a single keyframe there is no stereo).
- ``centered``: the paper's window ``[t - 2, t - 1, t, t + 1, t + 2]`` in keyframes: the reference is
  the keyframe two before the newest, the sources are the keyframes at most two keyframes away on
  either side (up to 4). The first reference is processed when the third keyframe arrives (with
  sources t + 1, t + 2 only), the second when the fourth arrives (t - 1, t + 1, t + 2), from the
  fifth on the window is full. Outputs therefore lag two keyframes behind the newest frame.

With a *pool* (``KeyframeWindow(capacity, pool=P)``, P > capacity) the window keeps the last P keyframes; the
reference is chosen as above (among the last ``capacity``, same latency), and when a ``score`` callable is
given to :meth:`KeyframeWindow.select` the ``capacity - 1`` sources are chosen from every pool keyframe the
mode allows (causal: older than the reference; centered: older, and the up to ``capacity // 2`` newer ones)
by :func:`dpv_sensor.core.parallax.select_sources`: how well each one's baseline and overlap constrain the
reference's depth, the closest in time among those that reach ``min_score``.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, List, Optional, Tuple

import numpy as np

from dpv_sensor import params as _params
from dpv_sensor.core.pose_math import pose_delta_np as pose_delta  # noqa: F401  (the one home: pose_math)

__all__ = ['pose_delta', 'KeyframeDecision', 'KeyframeSelector', 'Keyframe', 'KeyframeWindow', 'WINDOW_MODES']

WINDOW_MODES = _params.choices('window_mode')


@dataclass(frozen=True)
class KeyframeDecision:
    """Whether a frame is a keyframe and why (``first``, ``baseline``, ``rotation``, ``interval``) or
    why not (``none``); ``translation`` / ``rotation_deg`` are measured from the last keyframe."""
    is_keyframe: bool
    reason: str
    translation: float = 0.0
    rotation_deg: float = 0.0
    frames_since: int = 0


class KeyframeSelector:
    """Keyframe selection by baseline, rotation and a frame-count fallback (see the module docstring)."""

    def __init__(self, translation: float = 0.05, rotation_deg: float = 5.0, max_interval: int = 5):
        if translation < 0 or rotation_deg < 0:
            raise ValueError('keyframe thresholds must be >= 0')
        if int(max_interval) < 1:
            raise ValueError(f'max_interval must be >= 1, got {max_interval}')
        self.translation = float(translation)
        self.rotation_deg = float(rotation_deg)
        self.max_interval = int(max_interval)
        self._last_T: Optional[np.ndarray] = None
        self._since = 0

    def reset(self) -> None:
        """Forget the last keyframe: the next frame becomes a keyframe."""
        self._last_T = None
        self._since = 0

    @property
    def last_keyframe_pose(self) -> Optional[np.ndarray]:
        return None if self._last_T is None else self._last_T.copy()

    def peek(self, T_world_cam_44: np.ndarray) -> KeyframeDecision:
        """The decision for a frame with this pose, without changing the state."""
        if self._last_T is None:
            return KeyframeDecision(True, 'first')
        since = self._since + 1
        dt, dr = pose_delta(self._last_T, T_world_cam_44)
        if self.translation > 0 and dt >= self.translation:
            reason = 'baseline'
        elif self.rotation_deg > 0 and dr >= self.rotation_deg:
            reason = 'rotation'
        elif since >= self.max_interval:
            reason = 'interval'
        else:
            return KeyframeDecision(False, 'none', dt, dr, since)
        return KeyframeDecision(True, reason, dt, dr, since)

    def decide(self, T_world_cam_44: np.ndarray) -> KeyframeDecision:
        """Decide for the next frame and update the state (call once per accepted frame, in order)."""
        decision = self.peek(T_world_cam_44)
        if decision.is_keyframe:
            self._last_T = np.array(T_world_cam_44, dtype=np.float64, copy=True)
            self._since = 0
        else:
            self._since += 1
        return decision


@dataclass
class Keyframe:
    """One keyframe as the estimator keeps it.

    ``T_world_cam_44`` is the pose used for the plane sweep (the odometry pose, replaced by the pose
    refiner's result when one is set); ``odom_T_world_cam_44`` keeps the pose as received.
    ``image_b3hw`` is the processing-size image (float in [0, 1], on the estimator's device) and
    ``K_b33`` its intrinsics. ``cache`` holds per-keyframe results that must not be recomputed when the
    keyframe serves as a source again (network features). ``index`` counts keyframes since the last
    reset; ``frame_index`` counts accepted frames. ``twist_world_6`` is the camera's world-frame velocity
    (vx, vy, vz, wx, wy, wz) when the frame arrived, ``pose_cov_66`` and ``twist_cov_66`` the odometry's pose
    and twist covariance (ROS order), when known: what the pose uncertainty of the measurement is computed from
    (``dpv_sensor.core.pose_uncertainty``). ``camera_gray_u8`` is the image as received, in grey (uint8, at
    ``input_K_33``), kept only for a pose refiner whose ``uses_camera_images`` is true (its flow matches).
    """
    index: int
    frame_index: int
    stamp: float
    T_world_cam_44: np.ndarray
    image_b3hw: Any
    K_b33: Any
    input_size: Tuple[int, int]          # (width, height) of the frame as received
    input_K_33: np.ndarray
    frame_id: str = 'camera'
    odom_T_world_cam_44: Optional[np.ndarray] = None
    cache: Dict[str, Any] = field(default_factory=dict)
    twist_world_6: Optional[np.ndarray] = None
    pose_cov_66: Optional[np.ndarray] = None
    twist_cov_66: Optional[np.ndarray] = None
    camera_gray_u8: Optional[np.ndarray] = None

    def __post_init__(self):
        self.T_world_cam_44 = np.array(self.T_world_cam_44, dtype=np.float64, copy=True)
        if self.odom_T_world_cam_44 is None:
            self.odom_T_world_cam_44 = self.T_world_cam_44.copy()


class KeyframeWindow:
    """The last ``capacity`` keyframes, oldest first, and the reference/source choice of a window."""

    def __init__(self, capacity: int = 5, pool: int = 0):
        if capacity < 2:
            raise ValueError('a window needs at least 2 keyframes')
        self.capacity = int(capacity)
        self.pool = max(self.capacity, int(pool))
        self._kfs: deque = deque(maxlen=self.pool)

    def __len__(self) -> int:
        return len(self._kfs)

    def __getitem__(self, i: int) -> Keyframe:
        return self._kfs[i]

    def __iter__(self):
        return iter(self._kfs)

    @property
    def keyframes(self) -> List[Keyframe]:
        return list(self._kfs)

    def clear(self) -> None:
        self._kfs.clear()

    def append(self, kf: Keyframe) -> None:
        self._kfs.append(kf)

    @property
    def newest(self) -> Optional[Keyframe]:
        return self._kfs[-1] if self._kfs else None

    def lag(self, mode: str) -> int:
        """How many keyframes the reference trails the newest keyframe (0 causal, capacity//2 centered)."""
        if mode == 'causal':
            return 0
        if mode == 'centered':
            return self.capacity // 2
        raise ValueError(f'window mode must be one of {WINDOW_MODES}, got {mode!r}')

    def select(self, mode: str, score: Optional[Callable[[Keyframe, Keyframe], float]] = None,
               min_score: float = 0.0) -> Optional[Tuple[Keyframe, List[Keyframe]]]:
        """(reference, sources) for the newest window, or None while there is no stereo pair yet.

        Sources are in time order. ``causal``: reference = newest, sources = the up to ``capacity - 1``
        keyframes before it. ``centered``: reference = the keyframe ``lag`` before the newest; sources = the
        keyframes at most ``lag`` keyframes away from it (older and newer). With a pool and ``score(ref,
        candidate)`` (see the module docstring) the sources are chosen from the whole pool instead.
        """
        lag = self.lag(mode)
        n = len(self._kfs)
        if n < lag + 1 or n < 2:
            return None
        r = n - 1 - lag
        ref = self._kfs[r]
        if score is not None and self.pool > self.capacity:
            from dpv_sensor.core.parallax import select_sources
            cand = list(range(0, n)) if mode == 'centered' else list(range(0, r))
            cand = [i for i in cand if i != r]
            scores = [float(score(ref, self._kfs[i])) for i in cand]
            chosen = select_sources(r, cand, scores, self.capacity - 1, min_score)
            sources = [self._kfs[i] for i in chosen]
        elif mode == 'causal':
            sources = [self._kfs[i] for i in range(max(0, r - (self.capacity - 1)), r)]
        else:
            sources = [self._kfs[i] for i in range(max(0, r - lag), min(n, r + lag + 1)) if i != r]
        if not sources:
            return None
        return ref, sources
