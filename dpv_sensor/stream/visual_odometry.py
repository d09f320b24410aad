"""Frame-to-keyframe direct visual odometry for running without odometry (layer 5).

:class:`VisualOdometry` (``odometry: none``): a pose for every frame by aligning it against the last keyframe's
filtered depth and confidence (constant-velocity initialisation). Before the filter has produced any depth it
aligns against a bootstrap depth: ``depth_prior(image, K)`` if given (the measurement model's metric depth), else a
fronto-parallel plane at ``bootstrap_depth`` metres. Its poses replace odometry, and the same
:class:`~dpv_sensor.stream.window_refiner.WindowPoseRefiner` refines them.

Scale caveat: monocular alignment has no metric scale of its own. Translations are in the units of the depth it
aligns against, so the trajectory (and, through the plane sweep, the depth) is metric only as far as the bootstrap
depth is: the network's metric depth gives an approximately metric scale; the plane guess gives an arbitrary one
(evaluate it median-scaled), and the scale may drift over time in either case.

Tracking loss: an alignment that does not converge or a pose that jumps away from the constant-velocity prediction
by more than the configured thresholds sets ``tracking_ok = False`` with a reason; the estimator must not publish
depth computed with that pose, and the visual odometry re-bootstraps on the next frame.

Poses are float64 numpy 4x4 ``T_world_cam`` (camera-to-world, OpenCV axes). No ROS import.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Callable, Optional, Tuple

import gtsam
import numpy as np

from dpv_sensor.core.photometric import AlignmentConfig, AlignmentResult, Aligner, pose_error
from dpv_sensor.stream.window_graph import pose3_from_matrix, relative_pose

__all__ = ['VisualOdometryConfig', 'VOResult', 'VisualOdometry']


@dataclass
class VisualOdometryConfig:
    """Parameters of :class:`VisualOdometry`.

    alignment: photometric alignment parameters for frame-to-keyframe tracking (levels counted from an image
        of at most ``max_width`` pixels).
    max_width: VO runs on every frame: wider images are tracked on the pyramid level that brings them to at
        most this width (and coarser), i.e. ``finest_level`` and ``num_levels`` grow by the levels skipped.
    bootstrap_depth: depth (m) of the fronto-parallel plane used before any depth exists, when no depth prior
        callable is given (sets the scale of the trajectory: see the module doc).
    bootstrap_confidence: confidence given to the bootstrap depth.
    max_jump_translation_m, max_jump_rotation_deg: tracking is lost when the aligned pose is further than this
        from the constant-velocity prediction.
    constant_velocity: initialise from the constant-velocity prediction (else from the last pose).
    """
    alignment: AlignmentConfig = field(default_factory=lambda: AlignmentConfig(finest_level=1))
    max_width: int = 320
    bootstrap_depth: float = 2.0
    bootstrap_confidence: float = 1.0
    max_jump_translation_m: float = 0.15
    max_jump_rotation_deg: float = 10.0
    constant_velocity: bool = True


@dataclass
class VOResult:
    """Pose of one frame from :meth:`VisualOdometry.track`.

    T_world_cam_44: the estimated pose (after tracking loss: the constant-velocity prediction, which must not be
        used to publish depth). tracking_ok / reason: as for the refiner; reason is 'bootstrap' when this frame
        started a new reference (first frame or after a loss: tracking_ok is True, but the depth it aligns against
        is the bootstrap depth). alignment: the AlignmentResult (None for a bootstrap frame).
    """
    T_world_cam_44: np.ndarray
    tracking_ok: bool
    reason: Optional[str]
    alignment: Optional[AlignmentResult] = None
    bootstrap: bool = False


DepthPrior = Callable[[np.ndarray, np.ndarray], Tuple[np.ndarray, Optional[np.ndarray]]]


class VisualOdometry:
    """Frame-to-keyframe direct visual odometry for ``odometry: none``.

    Call :meth:`track` for every frame (in time order) to get its pose, and :meth:`set_keyframe` whenever the
    estimator has a filtered depth (and confidence) for a keyframe, with that keyframe's (refined) pose: later
    frames align against it. ``depth_prior(image_uint8_hw3, K_33) -> (depth_hw, conf_hw | None)`` supplies a
    metric depth for bootstrapping (the measurement model's); without it a plane at ``bootstrap_depth`` is used.
    The first frame defines the world frame (identity pose).
    """

    def __init__(self, config: Optional[VisualOdometryConfig] = None, depth_prior: Optional[DepthPrior] = None):
        self.config = config or VisualOdometryConfig()
        self.depth_prior = depth_prior
        self.reset()

    def reset(self) -> None:
        """Forget everything; the next frame restarts at the identity pose."""
        self._ref = None            # dict(image, K, T_world_cam, depth, conf, K_depth, bootstrap)
        self._last: Optional[Tuple[float, np.ndarray]] = None   # (stamp, T_world_cam) of the last tracked frame
        self._prev: Optional[Tuple[float, np.ndarray]] = None
        self._lost = False

    @property
    def has_keyframe_depth(self) -> bool:
        """True once a filtered keyframe depth (not the bootstrap depth) is the tracking reference."""
        return self._ref is not None and not self._ref['bootstrap']

    def predict(self, stamp: float) -> np.ndarray:
        """Constant-velocity prediction of the pose at ``stamp`` (identity before any frame)."""
        if self._last is None:
            return np.eye(4)
        t1, T1 = self._last
        if self._prev is None or not self.config.constant_velocity:
            return T1.copy()
        t0, T0 = self._prev
        xi = gtsam.Pose3.Logmap(pose3_from_matrix(relative_pose(T0, T1)))
        scale = (stamp - t1) / (t1 - t0) if t1 > t0 else 1.0
        scale = float(np.clip(scale, 0.0, 3.0))
        return T1 @ gtsam.Pose3.Expmap(xi * scale).matrix()

    def _config_for(self, image) -> AlignmentConfig:
        """The alignment config for an image of this width (extra pyramid levels above ``max_width``)."""
        shape = tuple(image.shape) if hasattr(image, 'shape') else np.asarray(image).shape
        if len(shape) == 3 and shape[0] in (1, 3) and shape[-1] not in (1, 3):
            w = shape[2]                                   # C x H x W tensor
        else:
            w = shape[1]                                   # H x W (x C)
        extra = 0
        while self.config.max_width > 0 and w / (2 ** extra) > self.config.max_width * 1.01:
            extra += 1
        a = self.config.alignment
        return dataclasses.replace(a, finest_level=a.finest_level + extra, num_levels=a.num_levels + extra)

    def _bootstrap(self, image, K_33, T_world_cam):
        if self.depth_prior is not None:
            depth, conf = self.depth_prior(image, K_33)
            depth = np.asarray(depth, dtype=np.float32)
            conf = None if conf is None else np.asarray(conf, dtype=np.float32)
        else:
            h, w = np.asarray(image).shape[:2]
            depth = np.full((h, w), self.config.bootstrap_depth, dtype=np.float32)
            conf = np.full((h, w), self.config.bootstrap_confidence, dtype=np.float32)
        self._ref = dict(T_world_cam=T_world_cam.copy(), bootstrap=True,
                         aligner=Aligner(image, depth, K_33, conf_ref=conf, config=self._config_for(image)))

    def track(self, image, K_33: np.ndarray, stamp: float) -> VOResult:
        """Pose of a new frame (see the class doc)."""
        cfg = self.config
        T_pred = self.predict(stamp)
        if self._ref is None or self._lost:
            # (Re)start: this frame is the reference, at the predicted pose (identity for the very first).
            self._bootstrap(image, K_33, T_pred)
            self._prev = None
            self._last = (stamp, T_pred.copy())
            self._lost = False
            return VOResult(T_pred, True, 'bootstrap', None, bootstrap=True)
        ref = self._ref
        T_src_ref0 = relative_pose(T_pred, ref['T_world_cam'])
        res = ref['aligner'].align(image, T_src_ref0)
        T_est = ref['T_world_cam'] @ res.T_ref_src_44
        reason = None if res.converged else f'alignment failed: {res.reason}'
        if reason is None:
            dt, dr = pose_error(T_pred, T_est)
            if dt > cfg.max_jump_translation_m or dr > cfg.max_jump_rotation_deg:
                reason = (f'pose jump {dt:.3f} m / {dr:.2f} deg from the constant-velocity prediction (limits '
                          f'{cfg.max_jump_translation_m} m / {cfg.max_jump_rotation_deg} deg)')
        if reason is not None:
            self._lost = True
            self._prev = None
            self._last = (stamp, T_pred.copy())
            return VOResult(T_pred, False, reason, res)
        self._prev, self._last = self._last, (stamp, T_est.copy())
        return VOResult(T_est, True, None, res)

    def set_keyframe(self, image, K_33: np.ndarray, T_world_cam_44: np.ndarray, depth_hw, conf_hw=None,
                     K_depth_33=None, stamp: Optional[float] = None) -> None:
        """Make a keyframe with the filter's depth (and confidence) the tracking reference.

        ``T_world_cam_44`` is the keyframe's (refined) pose; ``K_depth_33`` the intrinsics of the depth grid when
        it differs in size from the image (must be K_33 scaled). When ``stamp`` is the stamp of the latest tracked
        frame, the refined pose also replaces that frame's pose in the constant-velocity state (the previous pose
        moves with it, so the velocity is kept).
        """
        T = np.asarray(T_world_cam_44, dtype=np.float64)
        if stamp is not None and self._last is not None and abs(float(stamp) - self._last[0]) < 1e-9:
            correction = T @ np.linalg.inv(self._last[1])
            if self._prev is not None:
                self._prev = (self._prev[0], correction @ self._prev[1])
            self._last = (self._last[0], T.copy())
        self._ref = dict(T_world_cam=T.copy(), bootstrap=False,
                         aligner=Aligner(image, np.asarray(depth_hw, dtype=np.float32), K_33,
                                         conf_ref=None if conf_hw is None else np.asarray(conf_hw, dtype=np.float32),
                                         K_depth_33=K_depth_33, config=self._config_for(image)))
