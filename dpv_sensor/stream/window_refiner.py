"""Sliding-window pose refinement with gtsam (layer 5).

Paper sec. 3.4 (eq. 11): the depth and confidence predicted for the new reference keyframe (the filter's
previous belief warped into it) are used to re-estimate the relative poses of the window's source frames to the
reference by minimising the confidence-weighted robust photometric error. Here those photometric alignments
(:mod:`dpv_sensor.core.photometric`) become ``BetweenFactorPose3`` factors with the alignment's covariance (robustified
with a Huber norm) in a gtsam factor graph over the keyframes of the sliding window, next to odometry between
factors with configurable sigmas and a prior that fixes the gauge on the oldest keyframe; Levenberg-Marquardt
solves it at every keyframe. The graph and its solve are :mod:`dpv_sensor.stream.window_graph`; the keypoint
relative poses :mod:`dpv_sensor.core.keypoint_pose` (and :mod:`dpv_sensor.core.flow_rotation`); the configuration and
the records :mod:`dpv_sensor.stream.window_refiner_config`; this module decides what enters the graph and keeps the
window.

The refiner, :class:`WindowPoseRefiner` (``pose_refinement: window``): the estimator calls
:meth:`WindowPoseRefiner.refine` once per keyframe with the window's keyframes (their images and odometry poses) and
the reference's predicted depth/confidence; it returns refined ``T_world_cam`` of every window keyframe, the refined
``T_src_ref`` for the plane sweep, and a ``tracking_ok`` flag with a reason. It keeps its own state between calls
(refined poses, earlier alignment factors whose keyframes are still in the window). Visual odometry
(:mod:`dpv_sensor.stream.visual_odometry`, ``odometry: none``) produces poses that the same refiner refines.

Estimator integration: a :class:`WindowPoseRefiner` instance *is* the estimator's ``pose_refiner`` hook
(:meth:`WindowPoseRefiner.__call__` takes its ``PoseRefinementRequest`` and returns one ``T_world_cam`` per window
keyframe); after the call, :attr:`WindowPoseRefiner.tracking_lost` and ``last_result.reason`` report tracking
loss, and ``reset()`` forgets the window. Keyframes are keyed by stamp. The hook turns the DPV confidence into a
per-pixel inverse-depth std (:func:`~dpv_sensor.core.photometric.inverse_depth_std_from_confidence`).

What the alignments can and cannot correct: against the filter's predicted depth, photometric alignment pins the
rotation to a few hundredths of a degree but the translation only to a few percent of the baseline (the depth's
scale and structure errors enter it directly), and a constant inverse-depth error of the predicted depth - what
rotation errors leave in plane-swept depth - maps back onto a rotation about the axis normal to the baseline.
The factors' covariances are widened accordingly (``depth_scale_sigma``, ``inv_depth_offset_sigma``,
``translation_sigma_rel``). The defaults (5 % depth scale, 10 % of the step isotropically) still let the
alignments move the translation by about the odometry's own error: keeping the odometry's translation while the
alignments turn the rotation leaves a pose that agrees with neither, and plane-swept depth from such poses is
biased (measured with ``studies.poses``, classical model: with 50 % / 20 % widening, SUN3D recovered 0.22 and
-0.01 of the noisy-to-GT abs_rel gap; with 10 % / 5 % (and 2 sources per keyframe), 0.74 and 0.59, and rendered
sequences 0.87 and 0.81 instead of 0.82 and 0.79, at the same metric translation RPE).

Tracking loss: an alignment that does not converge (see :class:`~dpv_sensor.core.photometric.AlignmentResult`), too
few valid pixels, or a refined pose that jumps away from the odometry (or constant-velocity) prediction by more
than the configured thresholds sets ``tracking_ok = False`` with a reason. The estimator must then reset the
filter and not publish depth computed with that pose; the refiner itself discards the diverged solution (it keeps
the odometry-chained poses and drops its photometric factors), and the visual odometry re-bootstraps.

Poses are float64 numpy 4x4 ``T_world_cam`` (camera-to-world, OpenCV axes). No ROS import.
"""
from __future__ import annotations

import collections
import math
import time
from dataclasses import dataclass, field
from typing import Deque, Dict, Hashable, List, Optional, Sequence, Tuple

import gtsam
import numpy as np

from dpv_sensor.core import pose_uncertainty
from dpv_sensor.core.flow_rotation import RotationEstimate, flow_matches, match_image, rotation_given_direction
from dpv_sensor.core.keypoint_pose import (Features, KeypointPose, detect_features, keypoint_relative_pose,
                                           rotation_factor_covariance_gtsam)
from dpv_sensor.core.pose_math import rotation_angle_np
from dpv_sensor.core.odometry_covariance import OdometryCovariance
from dpv_sensor.core.photometric import (AlignmentResult, Aligner, ImagePyramid, inverse_depth_std_from_confidence,
                                         pose_error)
from dpv_sensor.stream.window_graph import (odometry_between_sigmas, odometry_step_covariance, odometry_steps,
                                            pose3_from_matrix, relative_marginal_sigmas, relative_pose,
                                            solve_window)
from dpv_sensor.stream.window_refiner_config import PairMatches, PoseRefinerConfig, RefinementResult, WindowKeyframe

#: per-axis variance (m^2) of the translation of a keypoint factor that holds only a rotation: 10 m std, nothing
#: next to the odometry's millimetres
_FREE_TRANSLATION_VAR = 100.0

#: the predicted depth's grid step (volume pixels, each axis) when the window reads only its median: on
#: tum_fr1_rpy's windows the median of every second pixel is within 1.3 % of the whole grid's (5-95 %, worst 2.3 %),
#: every fourth within 4 % (worst 8 %)
MEDIAN_DEPTH_STRIDE = 2

__all__ = ['PoseRefinerConfig', 'WindowKeyframe', 'RefinementResult', 'WindowPoseRefiner',
           'odometry_between_sigmas', 'odometry_step_covariance', 'relative_pose_errors', 'pose3_from_matrix',
           'relative_pose']


def relative_pose_errors(T_world_est: Sequence[np.ndarray], T_world_gt: Sequence[np.ndarray]
                         ) -> Tuple[np.ndarray, np.ndarray]:
    """Relative pose errors between consecutive poses: (translation m, rotation deg) arrays of length n-1."""
    t_err, r_err = [], []
    for i in range(1, len(T_world_est)):
        rel_est = np.linalg.inv(T_world_est[i - 1]) @ T_world_est[i]
        rel_gt = np.linalg.inv(T_world_gt[i - 1]) @ T_world_gt[i]
        te, re = pose_error(rel_gt, rel_est)
        t_err.append(te)
        r_err.append(re)
    return np.asarray(t_err), np.asarray(r_err)


# ------------------------------------------------------------------------------------------------------------------
# Sliding-window refiner
# ------------------------------------------------------------------------------------------------------------------

@dataclass
class _DepthReference:
    """What a window is aligned against: the reference's depth and its weights (the arguments of
    :meth:`WindowPoseRefiner.refine`)."""
    depth_hw: object
    conf_hw: object = None
    K_depth_33: Optional[np.ndarray] = None
    inv_depth_std_hw: object = None


@dataclass
class _WindowAlignments:
    """The photometric alignments of one window: per source the result (None: not tried), the sources tried
    (nearest first), why some are unusable, and the between factors of the usable ones."""
    alignments: List[Optional[AlignmentResult]]
    order: List[int] = field(default_factory=list)
    nearest: Optional[int] = None
    failed: Dict[int, str] = field(default_factory=dict)
    new_factors: list = field(default_factory=list)


class WindowPoseRefiner:
    """Sliding-window pose refinement: photometric alignments + odometry in a gtsam factor graph.

    Usage by the estimator, once per keyframe (after predicting the reference's DPV)::

        T_init = refiner.initial_pose(ref_key, T_world_cam_odom)      # odometry chained onto refined poses
        ... predict the DPV of the reference with T_init, depth_hat / conf_hat = eq. 1 / eq. 2 ...
        res = refiner.refine(WindowKeyframe(ref_key, ref_img, K, T_odom_ref),
                             [WindowKeyframe(k, img_k, K, T_odom_k) for the window's sources],
                             depth_hat, conf_hat, K_depth_33=K_volume)
        if not res.tracking_ok: reset the filter, do not publish this keyframe
        else: plane sweep with res.T_src_ref; predict/update the filter with res.T_world_ref_44

    ``reset()`` forgets everything (call it with the estimator's reset).
    """

    def __init__(self, config: Optional[PoseRefinerConfig] = None):
        self.config = config or PoseRefinerConfig()
        self.calls = 0          # refine() calls since construction (not cleared by reset)
        self.reset()

    def reset(self) -> None:
        self._odom: Dict[Hashable, np.ndarray] = {}       # first odometry pose seen per key
        self._est: Dict[Hashable, np.ndarray] = {}        # current refined pose per key
        self._factors: List[Tuple[Hashable, Hashable, np.ndarray, np.ndarray]] = []  # (ref, src, T_ref_src, cov)
        self._pyramids: Dict[Hashable, ImagePyramid] = {}   # per keyframe, reused while it stays in the window
        self._features: Dict[Hashable, Features] = {}       # keypoints per keyframe, likewise
        self._match_images: Dict[Hashable, Tuple[np.ndarray, np.ndarray]] = {}   # flow's (grey, K), likewise
        self._flow: Dict[Tuple[Hashable, Hashable], RotationEstimate] = {}   # flow rotation per pair in the window
        self._rotation_factors: Dict[Tuple[Hashable, Hashable], tuple] = {}  # flow factors (src, ref) kept
        # matched pixels per pair (a, b) in the window, flow's or SIFT's inliers: (pixels in a, pixels in b, K, the
        # flow's dense field from a to b or None)
        self._pair_matches: Dict[Tuple[Hashable, Hashable], tuple] = {}
        self._depth_refs = 0                                 # references with a predicted depth since the start
        self._cov: Dict[Hashable, Optional[OdometryCovariance]] = {}   # first odometry covariances seen per key
        self._graph = None                                   # (graph, result, index) of the last solve
        self._anchor_key: Optional[Hashable] = None          # the gauge keyframe of the last solve
        self.last_result: Optional[RefinementResult] = None
        self.losses = 0
        if not hasattr(self, 'gate_counts'):
            self.gate_counts: Dict[str, int] = {}   # windows per gate outcome since construction (not reset)
            # factors per decision since construction (not reset): photometric alignments used, inconsistent
            # (beyond photometric_gate_chi2), not_converged, jump; flow rotations used, no_texture, disagree (too
            # few matches agree on a rotation), undetermined; with rotation_evidence 'auto' windows whose rotation
            # factors came from the flow (evidence_flow) or from SIFT (evidence_keypoints: the images disagree with
            # the odometry's directions, or no pair has said yet)
            self.factor_counts: Dict[str, int] = {}
            # the last flow pairs' direction_ratio (rotation_evidence 'auto'): a property of the camera and the
            # odometry, so kept across resets
            self._direction_ratios: Deque[float] = collections.deque(maxlen=self.config.flow_direction_pairs)
            self._new_flow_pairs = 0                         # flow pairs measured since construction (not reset)

    @property
    def uses_camera_images(self) -> bool:
        """Whether the refiner matches the keyframes' images at the camera's resolution (flow rotation factors):
        only then does the estimator keep them (``Keyframe.camera_gray_u8``)."""
        return bool(self.config.keypoint_factors and self.config.rotation_evidence != 'keypoints')

    @property
    def predicted_depth_stride(self) -> int:
        """Every how many pixels of the volume grid the estimator needs the reference's predicted depth (each
        axis): the whole grid where the window aligns photometrically against it; else only its median is read
        (the turning-in-place test), which every second pixel gives within 1-2 % at a quarter of the warp."""
        aligns = self.config.max_sources is None or self.config.max_sources > 0
        return 1 if aligns else MEDIAN_DEPTH_STRIDE

    @property
    def direction_ratio(self) -> Optional[Tuple[float, float]]:
        """(the median of the last flow pairs' direction ratio, the threshold of rotation_evidence 'auto'); None
        before any flow pair has one."""
        if not self._direction_ratios:
            return None
        return float(np.median(self._direction_ratios)), float(self.config.flow_direction_ratio)

    @property
    def tracking_lost(self) -> bool:
        """True when the last :meth:`refine` flagged tracking loss (reason in ``last_result.reason``)."""
        return self.last_result is not None and not self.last_result.tracking_ok

    # ---------------------------------------------------------------------------------------------------------
    def __call__(self, request) -> Optional[List[np.ndarray]]:
        """The estimator's ``pose_refiner`` hook: ``(PoseRefinementRequest) -> list of T_world_cam``.

        ``request`` has ``keyframes`` (time order; each with ``stamp``, ``image_b3hw`` (1, 3, H, W) in [0, 1],
        ``K_b33``, ``odom_T_world_cam_44``), ``reference`` (index), ``depth_hw`` / ``confidence_hw`` (torch,
        volume resolution, or None) and ``K_depth_33``. Keyframes are keyed by their stamp. Returns one
        ``T_world_cam`` per keyframe in the request's order: refined, or after tracking loss the odometry
        motion chained onto the last refined poses (never a diverged pose). The outcome (``tracking_ok``,
        ``reason``, alignments, timings) is in :attr:`last_result` / :attr:`tracking_lost`.
        """
        kfs = list(request.keyframes)
        frames = []
        for kf in kfs:
            img = kf.image_b3hw
            img = img[0] if getattr(img, 'dim', lambda: 0)() == 4 else img
            K = kf.K_b33
            K = K[0] if getattr(K, 'dim', lambda: 0)() == 3 else K
            K = K.detach().double().cpu().numpy() if hasattr(K, 'detach') else np.asarray(K, dtype=np.float64)
            odom = getattr(kf, 'odom_T_world_cam_44', None)
            odom = kf.T_world_cam_44 if odom is None else odom
            frames.append(WindowKeyframe(float(kf.stamp), img.detach().float().cpu() if hasattr(img, 'detach')
                                         else img, K, np.asarray(odom, dtype=np.float64),
                                         getattr(kf, 'pose_cov_66', None), getattr(kf, 'twist_cov_66', None),
                                         float(kf.stamp), getattr(kf, 'camera_gray_u8', None),
                                         getattr(kf, 'input_K_33', None)))
        r = int(request.reference)
        depth = request.depth_hw
        conf = request.confidence_hw
        depth = depth.detach().float().cpu() if depth is not None and hasattr(depth, 'detach') else depth
        conf = conf.detach().float().cpu() if conf is not None and hasattr(conf, 'detach') else conf
        rho_std = None
        depths_d = getattr(request, 'depths_d', None)
        if self.config.use_depth_uncertainty and conf is not None and depths_d is not None:
            rho_std = inverse_depth_std_from_confidence(conf, depths_d.detach().cpu()
                                                        if hasattr(depths_d, 'detach') else depths_d)
        res = self.refine(frames[r], [f for i, f in enumerate(frames) if i != r], depth, conf,
                          request.K_depth_33, rho_std)
        return [res.T_world_cam[f.key] for f in frames]

    # ---------------------------------------------------------------------------------------------------------
    @property
    def window_keys(self) -> List[Hashable]:
        return sorted(self._est)

    def initial_pose(self, key: Hashable, T_world_cam_odom_44: np.ndarray) -> np.ndarray:
        """Best pose of a keyframe before refinement: its refined pose if known, else the odometry motion from the
        nearest refined keyframe chained onto that keyframe's refined pose (falls back to the odometry pose)."""
        if key in self._est:
            return self._est[key].copy()
        T_odom = self._odom.get(key, np.asarray(T_world_cam_odom_44, dtype=np.float64))
        if not self._est:
            return T_odom.copy()
        anchor = self._nearest_known(key)
        return self._est[anchor] @ relative_pose(self._odom[anchor], T_odom)

    def _nearest_known(self, key: Hashable) -> Hashable:
        known = sorted(self._est)
        older = [k for k in known if k <= key]
        return older[-1] if older else known[0]

    # ---------------------------------------------------------------------------------------------------------
    def refine(self, ref: WindowKeyframe, sources: Sequence[WindowKeyframe], depth_ref=None, conf_ref=None,
               K_depth_33=None, inv_depth_std_ref=None) -> RefinementResult:
        """Refine the window's keyframe poses (see the class doc).

        Args:
            ref: the reference keyframe (the one whose depth is being estimated).
            sources: the other keyframes of the window (older and, for a centred window, newer ones).
            depth_ref: predicted depth of the reference (h, w) in metres, 0/NaN = none; None = nothing to align
                against (first keyframe, right after a reset): the poses are the odometry-chained ones.
            conf_ref: its confidence (h, w) in [0, 1] (paper eq. 2), None = uniform.
            K_depth_33: intrinsics of the depth grid when it differs in size from the images (e.g. the quarter-
                resolution volume); must be ``ref.K_33`` scaled.
            inv_depth_std_ref: optional per-pixel std of the inverse depth (1/m) on the depth grid: uncertain depth
                then weighs less in the alignment and widens its covariance.
        """
        t0 = time.perf_counter()
        c0 = time.process_time()
        self.calls += 1
        keys = [ref.key] + [f.key for f in sources]
        window = self._admit_window([ref] + list(sources))
        init = self._initial_values(window)
        t_align = time.perf_counter()
        warm = self._count_depth_ref(keys, depth_ref)
        skipped = None
        if depth_ref is not None and sources and warm:
            skipped = self._turning_in_place(ref, sources, init, depth_ref)
        if skipped is None and depth_ref is not None and sources and warm:
            depth = _DepthReference(depth_ref, conf_ref, K_depth_33, inv_depth_std_ref)
            aligned = self._align_sources(ref, sources, init, depth)
        else:
            aligned = _WindowAlignments(alignments=[None] * len(sources))
        t_opt = time.perf_counter()
        reason = self._alignment_failure(aligned)
        if skipped is not None:
            # a fallback, not a loss: the odometry-chained poses, and no photometric history across the turn
            self._factors = []
        kp_factors, kps, kp_huber_k = [], [], self.config.keypoint_huber_k
        t_kp = time.perf_counter()
        if self.config.keypoint_factors and sources and skipped is None and reason is None:
            flow = self._flow_factors(ref, sources, init) if self.config.rotation_evidence != 'keypoints' else None
            if flow is not None:
                kp_factors, kp_huber_k = flow, self.config.flow_huber_k
            else:
                kp_factors, kps = self._keypoint_factors(ref, sources, init)
        keypoints_ms = 1e3 * (time.perf_counter() - t_kp)
        factors = self._factors + aligned.new_factors
        gate = self._evidence_gate(kps, kp_factors, skipped)
        if gate != 'none':
            factors, kp_factors = [], []
        self._graph = None
        poses, refined, reason = self._solve(window, init, factors, reason, kp_factors, kp_huber_k)
        tracking_ok = reason is None
        if not tracking_ok:
            self.losses += 1
            poses, refined = init, False
            gate = 'lost'
        elif refined:
            gate = 'refined'
        if gate == 'none':
            gate = 'kept_no_factors'
        correction = self._correction(window, poses)
        self.gate_counts[gate] = self.gate_counts.get(gate, 0) + 1
        self._keep_solution(window, poses, factors, tracking_ok)
        sigmas = self._marginal_sigmas(window, ref, sources) if refined and self.config.marginals else {}
        t1 = time.perf_counter()
        T_world_ref = poses[ref.key]
        self.last_result = RefinementResult(
            T_world_cam={k: poses[k].copy() for k in window},
            T_world_ref_44=T_world_ref.copy(),
            T_src_ref=[relative_pose(poses[s.key], T_world_ref) for s in sources],
            tracking_ok=tracking_ok, reason=reason, refined=refined, alignments=aligned.alignments,
            timings_ms={'align': 1e3 * (t_opt - t_align), 'keypoints': keypoints_ms,
                        'optimize': 1e3 * (t1 - t_opt) - keypoints_ms, 'total': 1e3 * (t1 - t0),
                        'cpu': 1e3 * (time.process_time() - c0)}, skipped=skipped,
            source_sigma=sigmas, gate=gate, correction=correction, keypoints=kps,
            factors=self._factor_pairs(window, factors, kp_factors) if refined else {},
            odometry=odometry_steps(window, self._odom, self._cov, self.config),
            matches=self._reference_matches(ref.key, window),
            match_images={k: g for k, (g, _K) in self._match_images.items() if k in window})
        return self.last_result

    def _admit_window(self, frames: List[WindowKeyframe]) -> List[Hashable]:
        """Take the window's keyframes in (their odometry poses) and forget the keyframes that left it, with their
        factors; returns the window's keys in order."""
        keys = [f.key for f in frames]
        if len(set(keys)) != len(keys):
            raise ValueError(f'duplicate keys in the window: {keys}')
        for f in frames:
            if f.key not in self._odom:
                self._odom[f.key] = np.asarray(f.T_world_cam_odom_44, dtype=np.float64).copy()
                self._cov[f.key] = f.odometry_covariance()
        for store in (self._est, self._odom, self._pyramids, self._features, self._cov, self._match_images):
            for k in list(store):
                if k not in keys:
                    del store[k]
        for store in (self._flow, self._rotation_factors, self._pair_matches):
            for a, b in list(store):
                if a not in keys or b not in keys:
                    del store[(a, b)]
        if self.config.keep_old_factors:
            self._factors = [f for f in self._factors if f[0] in keys and f[1] in keys]
        else:
            self._factors = []
        return sorted(keys)

    def _count_depth_ref(self, keys: List[Hashable], depth_ref) -> bool:
        """Count a window with a depth to align against; whether enough came in a row to align (the warm-up)."""
        if depth_ref is not None:
            if not set(keys) & set(self._est):
                self._depth_refs = 0                         # a new stream: the window shares nothing with ours
            self._depth_refs += 1
        return self._depth_refs > self.config.warmup_keyframes

    def _align_sources(self, ref: WindowKeyframe, sources: Sequence[WindowKeyframe],
                       init: Dict[Hashable, np.ndarray], depth: '_DepthReference') -> '_WindowAlignments':
        """Align the nearest sources to the reference's depth; each usable alignment becomes a between factor."""
        cfg = self.config
        out = _WindowAlignments(alignments=[None] * len(sources))
        order = sorted(range(len(sources)), key=lambda i: _key_distance(sources[i].key, ref.key))
        if cfg.max_sources is not None:
            order = order[:cfg.max_sources]
        out.order = order
        if not order:                                   # max_sources 0: no photometric factors
            return out
        aligner = Aligner(self._pyramid(ref), depth.depth_hw, ref.K_33, conf_ref=depth.conf_hw,
                          K_depth_33=depth.K_depth_33, inv_depth_std_ref=depth.inv_depth_std_hw,
                          config=cfg.alignment)
        offset_sigma = cfg.inv_depth_offset_sigma
        if offset_sigma is None:
            base = float(np.linalg.norm(relative_pose(init[sources[order[0]].key], init[ref.key])[:3, 3]))
            offset_sigma = math.radians(cfg.odom_sigma_rot_deg) / max(base, 1e-3)
        for i in order:
            s = sources[i]
            T_src_ref0 = relative_pose(init[s.key], init[ref.key])
            res = aligner.align(self._pyramid(s), T_src_ref0)
            out.alignments[i] = res
            if not res.converged:
                out.failed[i] = res.reason
                self._count('photometric_not_converged')
                continue
            # A converged alignment that lands far from the odometry prediction is a pose jump.
            dt, dr = pose_error(T_src_ref0, res.T_src_ref_44)
            if dt > cfg.max_jump_translation_m or dr > cfg.max_jump_rotation_deg:
                out.failed[i] = (f'pose jump: the alignment moved {dt:.3f} m / {dr:.2f} deg away from the odometry '
                                 f'(limits {cfg.max_jump_translation_m} m / {cfg.max_jump_rotation_deg} deg)')
                self._count('photometric_jump')
                continue
            if cfg.photometric_gate_chi2 > 0 and not self._consistent_with_odometry(ref, s, T_src_ref0, res):
                self._count('photometric_inconsistent')
                continue
            self._count('photometric_used')
            out.new_factors.append((ref.key, s.key, res.T_ref_src_44,
                                    res.between_covariance_gtsam(cfg.depth_scale_sigma, cfg.translation_sigma_rel,
                                                                 offset_sigma)))
        out.nearest = order[0] if order else None
        return out

    def _count(self, decision: str) -> None:
        self.factor_counts[decision] = self.factor_counts.get(decision, 0) + 1

    def _consistent_with_odometry(self, ref: WindowKeyframe, src: WindowKeyframe, T_src_ref0: np.ndarray,
                                  res: AlignmentResult) -> bool:
        """Whether the rotation an alignment moves the source by is within ``photometric_gate_chi2`` of what the
        odometry's rotation covariance between the two keyframes allows (3 dof)."""
        chi2 = self._rotation_chi2(src.key, ref.key, T_src_ref0, res.T_src_ref_44)
        return chi2 <= self.config.photometric_gate_chi2

    def _rotation_chi2(self, key_a: Hashable, key_b: Hashable, T_from_44: np.ndarray, T_to_44: np.ndarray,
                       extra_rot_cov_33: Optional[np.ndarray] = None) -> float:
        """``d^T (S + extra)^-1 d`` of the rotation ``d`` that takes relative pose ``T_from`` to ``T_to``, ``S`` the
        odometry's rotation covariance between keyframes ``key_a`` and ``key_b`` (either order) and ``extra`` the
        other estimate's, if any: how far a correction is from what the odometry's uncertainty allows (3 dof)."""
        d = gtsam.Pose3.Logmap(pose3_from_matrix(T_from_44).between(pose3_from_matrix(T_to_44)))[:3]
        a, b = (key_a, key_b) if key_a <= key_b else (key_b, key_a)     # in time order (keys order keyframes)
        S = odometry_step_covariance(self._odom[a], self._odom[b], self._cov.get(a), self._cov.get(b),
                                     self.config)[:3, :3]
        if extra_rot_cov_33 is not None:
            S = S + extra_rot_cov_33
        return float(d @ np.linalg.solve(S, d))

    def _alignment_failure(self, aligned: '_WindowAlignments') -> Optional[str]:
        """Why the window's alignments are not enough to refine it (None: they are, or none was tried)."""
        cfg = self.config
        order, failed = aligned.order, aligned.failed
        if not order:
            return None
        n_ok = len(order) - len(failed)
        if cfg.require_nearest and aligned.nearest in failed:
            return f'alignment to the nearest keyframe failed: {failed[aligned.nearest]}'
        if n_ok < cfg.min_converged_fraction * len(order):
            fails = '; '.join(sorted(set(failed.values())))
            return f'only {n_ok}/{len(order)} alignments usable ({fails})'
        return None

    def _keypoint_factors(self, ref: WindowKeyframe, sources: Sequence[WindowKeyframe],
                          init: Dict[Hashable, np.ndarray]) -> Tuple[list, List[KeypointPose]]:
        """Keypoint relative poses of the reference to its nearest sources; usable ones as (src, ref, T_src_ref,
        cov) between factors, the translation's length the odometry's."""
        cfg = self.config
        order = sorted(range(len(sources)), key=lambda i: _key_distance(sources[i].key, ref.key))
        factors, kps = [], []
        for i in order[:cfg.keypoint_sources]:
            s = sources[i]
            T0 = relative_pose(init[s.key], init[ref.key])                # T_src_ref from the odometry
            kp = keypoint_relative_pose(self._keypoints(ref), self._keypoints(s), ref.K_33, cfg.keypoint, T0,
                                        cfg.keypoint_prior_gate_px)
            kps.append(kp)
            if kp.pa_n2 is not None:
                self._pair_matches[(ref.key, s.key)] = (kp.pa_n2, kp.pb_n2, np.asarray(ref.K_33, np.float64), None)
            if not kp.ok or kp.t_dir_b is None:
                continue
            base = float(np.linalg.norm(T0[:3, 3]))
            T = np.eye(4)
            if cfg.keypoint_direction == 'odometry':
                # the rotation given the odometry's direction; the translation (the odometry's) is left free
                T[:3, :3], cov_rot = kp.rotation_given_direction(T0[:3, 3])
                T[:3, 3] = T0[:3, 3]
                cov = kp.rotation_covariance_gtsam(cov_rot, _FREE_TRANSLATION_VAR)
            elif cfg.keypoint_direction == 'keypoints':
                T[:3, :3] = kp.R_b_a
                T[:3, 3] = base * kp.t_dir_b
                cov = kp.between_covariance_gtsam(base, cfg.keypoint_scale_sigma_rel)
            else:
                raise ValueError(f"keypoint_direction must be 'keypoints' or 'odometry', not "
                                 f"{cfg.keypoint_direction!r}")
            factors.append((s.key, ref.key, T, cov))
        return factors, kps

    def _flow_factors(self, ref: WindowKeyframe, sources: Sequence[WindowKeyframe],
                      init: Dict[Hashable, np.ndarray]) -> Optional[list]:
        """Flow rotation factors (src, ref, T_src_ref, cov) between the reference and its ``keypoint_sources``
        nearest sources, the rotation given the odometry's direction and the translation left free, plus the kept
        factors of earlier windows between keyframes still in the window
        (:attr:`PoseRefinerConfig.rotation_evidence`): with a centred window every pair of neighbours is tied, at
        one new flow per keyframe. None with rotation_evidence 'auto' when the recent pairs' median
        ``direction_ratio`` is above ``flow_direction_ratio`` (or no pair has one yet): the caller takes SIFT's."""
        cfg = self.config
        if cfg.rotation_evidence == 'auto' and not self._probe_flow():
            self._count('evidence_keypoints')
            self._rotation_factors.clear()
            return None
        nearest = sorted(sources, key=lambda f: _key_distance(f.key, ref.key))[:cfg.keypoint_sources]
        estimates = []
        for s in nearest:
            T0 = relative_pose(init[s.key], init[ref.key])                # T_src_ref from the odometry
            estimates.append((s, T0, self._pair_rotation(ref, s, T0)))
        if cfg.rotation_evidence == 'auto':
            agree = self.direction_ratio is not None and self.direction_ratio[0] <= cfg.flow_direction_ratio
            self._count('evidence_flow' if agree else 'evidence_keypoints')
            if not agree:
                self._rotation_factors.clear()
                return None
        for s, T0, est in estimates:
            self._count('flow_used' if est.ok else f'flow_{est.kind}')
            if not est.ok:
                self._rotation_factors.pop((s.key, ref.key), None)
                continue
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = est.R_b_a, T0[:3, 3]
            cov = rotation_factor_covariance_gtsam(est.cov_33, est.R_b_a, _FREE_TRANSLATION_VAR)
            self._rotation_factors[(s.key, ref.key)] = (s.key, ref.key, T, cov)
        return list(self._rotation_factors.values())

    def _settled(self) -> Optional[bool]:
        """rotation_evidence 'auto': None while fewer than ``flow_direction_pairs // 5`` pairs have a direction
        ratio, else whether their median says the images agree with the odometry's directions."""
        if len(self._direction_ratios) < max(1, self.config.flow_direction_pairs // 5):
            return None
        return self.direction_ratio[0] <= self.config.flow_direction_ratio

    def _probe_flow(self) -> bool:
        """rotation_evidence 'auto': whether this window measures the flow. Once enough pairs say the images
        disagree with the odometry's directions (:meth:`_settled`), only every ``flow_probe_every``-th window does
        (what SIFT's factors cost, plus a flow now and then to notice if that changes)."""
        return self._settled() is not False or self.calls % max(1, self.config.flow_probe_every) == 0

    def _measure_direction_ratio(self) -> bool:
        """rotation_evidence 'auto': whether the next new flow pair also measures its direction ratio (a third of
        its fit's time). Once enough pairs say the images agree (:meth:`_settled`), only every
        ``flow_probe_every``-th new pair does: the median follows the camera at a quarter of the pairs."""
        if self.config.rotation_evidence != 'auto':
            return False
        self._new_flow_pairs += 1
        return self._settled() is not True or self._new_flow_pairs % max(1, self.config.flow_probe_every) == 0

    def _pair_rotation(self, ref: WindowKeyframe, src: WindowKeyframe, T0_src_ref: np.ndarray) -> RotationEstimate:
        """The flow rotation ``R_src_ref`` of a pair, given the direction of ``T0_src_ref``: measured once per pair
        while both keyframes stay in the window (the flow from the reference into the source, and with
        rotation_evidence 'auto' its direction ratio), the pair seen the other way round is the same estimate
        inverted: fitted with the direction and start of the window that first saw the pair (the next window's
        refined direction would move it to second order only), and a pair without an estimate stays without."""
        if (ref.key, src.key) in self._flow:
            return self._flow[(ref.key, src.key)]
        if (src.key, ref.key) in self._flow:
            return self._flow[(src.key, ref.key)].inverse()
        (ga, K), (gb, _) = self._match_image(ref), self._match_image(src)
        cfg = self.config
        matches = flow_matches(ga, gb, K, cfg.flow)
        self._pair_matches[(ref.key, src.key)] = (matches.pa_n2, matches.pb_n2, matches.K_33, matches.flow_hw2)
        est = rotation_given_direction(matches, T0_src_ref[:3, 3], T0_src_ref[:3, :3],
                                       cfg.flow, direction_ratio=self._measure_direction_ratio())
        if est.direction_ratio is not None:
            self._direction_ratios.append(est.direction_ratio)
        self._flow[(ref.key, src.key)] = est
        return est

    def _match_image(self, f: WindowKeyframe) -> Tuple[np.ndarray, np.ndarray]:
        if f.key not in self._match_images:
            image, K = (f.image, f.K_33) if f.camera_image is None else (f.camera_image, f.camera_K_33)
            self._match_images[f.key] = match_image(image, K, self.config.flow)
        return self._match_images[f.key]

    def _reference_matches(self, ref_key: Hashable, window: List[Hashable]) -> List[PairMatches]:
        """The matches of the window's pairs: those that include the reference, and the flow's between any two
        keyframes of the window (they chain into tracks through the reference), each with the odometry's per-axis
        std of the pair's relative pose."""
        out = []
        for (a, b), (pa, pb, K, flow) in self._pair_matches.items():
            if a not in window or b not in window or (ref_key not in (a, b) and flow is None):
                continue
            first, last = (a, b) if a <= b else (b, a)
            cov = odometry_step_covariance(self._odom[first], self._odom[last], self._cov.get(first),
                                           self._cov.get(last), self.config)
            out.append(PairMatches(a, b, pa, pb, K, math.sqrt(float(np.max(np.diag(cov)[:3]))),
                                   math.sqrt(float(np.max(np.diag(cov)[3:]))), flow))
        return out

    def _evidence_gate(self, kps: List[KeypointPose], kp_factors: list, skipped) -> str:
        """Before the solve: 'kept_few_inliers' when keypoint evidence is required and no pair has enough inliers;
        'rejected_chi2' when a keypoint rotation differs from the odometry's by more than ``gate_chi2`` allows
        under the sum of the two rotation covariances (d^T (S_odom + S_kp)^-1 d); else 'none'."""
        cfg = self.config
        if skipped is not None:
            return 'skipped'
        if cfg.keypoint_factors and cfg.gate_min_inliers > 0 and kps:
            if max(k.inliers for k in kps) < cfg.gate_min_inliers:
                return 'kept_few_inliers'
        if cfg.gate_chi2 > 0:
            for s, r, T_src_ref, cov in kp_factors:
                T_odom = relative_pose(self._odom[s], self._odom[r])
                if self._rotation_chi2(s, r, T_odom, T_src_ref, cov[:3, :3]) > cfg.gate_chi2:
                    return 'rejected_chi2'
        return 'none'

    def _correction(self, window, poses) -> Tuple[float, float]:
        """The largest change (m, deg) the refinement made to a step's odometry motion in this window."""
        worst = (0.0, 0.0)
        for a, b in zip(window[:-1], window[1:]):
            dt, dr = pose_error(relative_pose(self._odom[a], self._odom[b]), relative_pose(poses[a], poses[b]))
            worst = (max(worst[0], dt), max(worst[1], dr))
        return worst

    def _marginal_sigmas(self, window, ref, sources) -> Dict[Hashable, pose_uncertainty.PoseSigma]:
        """Per source, per-axis stds of its pose relative to the reference from the solved graph's marginals."""
        if self._graph is None:
            return {}
        return relative_marginal_sigmas(self._graph, ref.key, [s.key for s in sources])

    def _solve(self, window: List[Hashable], init: Dict[Hashable, np.ndarray], factors: list,
               reason: Optional[str], kp_factors: Sequence = (), kp_huber_k: Optional[float] = None
               ) -> Tuple[Dict[Hashable, np.ndarray], bool, Optional[str]]:
        """Optimise the window over its factors unless a reason says not to; returns (poses, refined, reason).
        ``kp_huber_k``: the rotation factors' Huber threshold (None: ``keypoint_huber_k``)."""
        if reason is not None or not (factors or kp_factors):
            return init, False, reason
        try:
            poses = self._optimize(window, init, factors, kp_factors, kp_huber_k)
        except RuntimeError as e:      # gtsam raises on indeterminate systems
            return init, False, f'window optimisation failed: {e}'
        return poses, True, self._jump_check(window, poses)

    def _keep_solution(self, window: List[Hashable], poses: Dict[Hashable, np.ndarray], factors: list,
                       tracking_ok: bool) -> None:
        """Keep a tracked window's poses and factors; after a loss keep the odometry-chained poses (``poses``
        then are those) and no photometric history."""
        self._est = {k: poses[k] for k in window}
        if tracking_ok:
            self._factors = factors
        else:
            self._factors = []
            self._depth_refs = 0

    def _turning_in_place(self, ref, sources, init, depth_ref) -> Optional[str]:
        """Why the window is not refined (``PoseRefinerConfig.max_rotation_parallax``), or None."""
        limit = self.config.max_rotation_parallax
        if not limit > 0:
            return None
        d = np.asarray(depth_ref.numpy() if hasattr(depth_ref, 'numpy') else depth_ref, dtype=np.float64)
        d = d[np.isfinite(d) & (d > 0)]
        if d.size == 0:
            return None
        nearest = min(sources, key=lambda s: _key_distance(s.key, ref.key))
        rel = relative_pose(init[nearest.key], init[ref.key])
        parallax = float(np.linalg.norm(rel[:3, 3])) / float(np.median(d))
        angle = rotation_angle_np(rel[:3, :3])
        if angle > limit * parallax:
            return (f'turning in place: {math.degrees(angle):.1f} deg to the nearest keyframe against a baseline of '
                    f'{parallax:.4f} x the median depth (ratio {angle / max(parallax, 1e-12):.1f} > {limit:g})')
        return None

    def _keypoints(self, f: WindowKeyframe) -> Features:
        if f.key not in self._features:
            self._features[f.key] = detect_features(f.image, self.config.keypoint)
        return self._features[f.key]

    def _pyramid(self, f: WindowKeyframe) -> ImagePyramid:
        if f.key not in self._pyramids:
            self._pyramids[f.key] = ImagePyramid(f.image, f.K_33, self.config.alignment.num_levels)
        return self._pyramids[f.key]

    # ---------------------------------------------------------------------------------------------------------
    def _initial_values(self, window: List[Hashable]) -> Dict[Hashable, np.ndarray]:
        if not self._est:
            # No refined pose yet: start from the odometry (the world frame of the odometry).
            return {k: self._odom[k].copy() for k in window}
        init = {}
        for k in window:
            init[k] = self.initial_pose(k, self._odom[k])
        return init

    def _anchor(self, window) -> Hashable:
        """The gauge: the oldest keyframe that already has a refined pose (else the oldest) stays where it is."""
        return next((k for k in window if k in self._est), window[0])

    def _factor_pairs(self, window, factors, kp_factors) -> Dict[str, List[Tuple[Hashable, Hashable]]]:
        """The factors :func:`solve_window` put in the graph, as key pairs by kind (``RefinementResult.factors``)."""
        keys = set(window)
        return {'prior': [(self._anchor_key, self._anchor_key)],
                'odometry': list(zip(window[:-1], window[1:])),
                'photometric': [(r, s) for r, s, _T, _c in factors if r in keys and s in keys],
                'keypoint': [(s, r) for s, r, _T, _c in kp_factors]}

    def _optimize(self, window, init, factors, kp_factors=(), kp_huber_k: Optional[float] = None
                  ) -> Dict[Hashable, np.ndarray]:
        anchor = self._anchor_key = self._anchor(window)
        poses, self._graph = solve_window(window, init, self._odom, self._cov, anchor, factors, kp_factors,
                                          self.config, kp_huber_k)
        return poses

    def _jump_check(self, window, poses) -> Optional[str]:
        cfg = self.config
        for a, b in zip(window[:-1], window[1:]):
            dt, dr = pose_error(relative_pose(self._odom[a], self._odom[b]), relative_pose(poses[a], poses[b]))
            if dt > cfg.max_jump_translation_m or dr > cfg.max_jump_rotation_deg:
                return (f'pose jump between keyframes {a} and {b}: {dt:.3f} m / {dr:.2f} deg away from odometry '
                        f'(limits {cfg.max_jump_translation_m} m / {cfg.max_jump_rotation_deg} deg)')
        return None


def _key_distance(a, b) -> float:
    try:
        return abs(float(a) - float(b))
    except (TypeError, ValueError):
        return 0.0
