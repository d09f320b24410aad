"""The sliding window's factor graph (gtsam), as :class:`~dpv_sensor.stream.window_refiner.WindowPoseRefiner`
solves it at every keyframe: a prior that fixes the gauge on one keyframe, odometry between factors from each
keyframe to the next (the configured sigmas, or what the odometry says about itself: ``odom_covariance``), the
photometric alignments and the keypoint relative poses as robust (Huber) between factors, Levenberg-Marquardt, and
each source's pose covariance relative to the reference from the solved graph's marginals.

``cfg`` is a :class:`~dpv_sensor.stream.window_refiner.PoseRefinerConfig` (its sigma, Huber and iteration fields).
Poses are float64 numpy 4x4 ``T_world_cam``; factors are ``(key_i, key_j, T_i_j, cov_66)`` with gtsam's tangent
order (rotation, translation). No ROS import.
"""
from __future__ import annotations

import math
from collections import Counter
from typing import Dict, Hashable, Mapping, NamedTuple, Optional, Sequence, Tuple

import gtsam
import numpy as np

from dpv_sensor.core import pose_uncertainty

__all__ = ['odometry_between_sigmas', 'odometry_step_covariance', 'odometry_step_source', 'OdometrySteps',
           'odometry_steps', 'pose3_from_matrix', 'relative_pose', 'solve_window', 'relative_marginal_sigmas']

# where an odometry step's covariance comes from (odometry_step_source)
FIXED = 'fixed sigmas'
PUBLISHED, TWIST, DRIFT = pose_uncertainty.GROWTH, pose_uncertainty.TWIST, pose_uncertainty.DRIFT
# an odometry step's per-axis std never goes below these (odometry is never exact)
STEP_FLOOR_ROT_DEG, STEP_FLOOR_TRANS_M = 1e-3, 1e-4


class OdometrySteps(NamedTuple):
    """The odometry factors of a window: the median per-axis std of its steps (rotation rad, translation m) and
    where their covariance came from (the source of most steps: ``FIXED``, ``PUBLISHED`` (the growth of the pose
    covariance), ``TWIST`` (the twist covariance) or ``DRIFT``)."""
    rot_rad: float
    trans_m: float
    source: str


def odometry_between_sigmas(T_a_b_44: np.ndarray, cfg) -> np.ndarray:
    """gtsam-ordered (rot, rot, rot, trans, trans, trans) sigmas of an odometry between factor for step T_a_b."""
    rot = math.radians(cfg.odom_sigma_rot_deg)
    tr = cfg.odom_sigma_trans_m + cfg.odom_sigma_trans_rel * float(np.linalg.norm(np.asarray(T_a_b_44)[:3, 3]))
    return np.array([rot, rot, rot, tr, tr, tr])


def odometry_step_covariance(T_odom_a: np.ndarray, T_odom_b: np.ndarray, cov_a, cov_b, cfg) -> np.ndarray:
    """gtsam-ordered 6x6 covariance of the odometry's motion from keyframe a to b (a the earlier): with
    ``odom_covariance='fixed'`` the configured sigmas; with 'odometry' what the odometry says about itself
    (``cov_a`` / ``cov_b``: :class:`~dpv_sensor.core.odometry_covariance.OdometryCovariance`, a bare 6x6 pose
    covariance, or None; :func:`dpv_sensor.core.pose_uncertainty.odometry_sigma`: the growth of the pose covariance,
    else the twist covariance over the step), else the drift figures of the step.

    Per axis never below 0.001 deg / 0.1 mm (odometry is never exact) and never above the window's jump limits
    (``max_jump_rotation_deg``, ``max_jump_translation_m``): a correction larger than those counts as lost tracking
    anyway, so a looser factor would say nothing more. A huge or jumping covariance thus makes a loose factor (the
    images decide within the limits), never a stiff one."""
    T_ab = relative_pose(T_odom_a, T_odom_b)
    if cfg.odom_covariance == 'fixed':
        return np.diag(odometry_between_sigmas(T_ab, cfg) ** 2)
    if cfg.odom_covariance != 'odometry':
        raise ValueError(f"odom_covariance must be 'fixed' or 'odometry', not {cfg.odom_covariance!r}")
    sig = pose_uncertainty.relative_pose_sigma(cfg.drift, [T_odom_a, T_odom_b], odom_first=cov_a, odom_last=cov_b)
    rot = _bounded(sig.rot_rad, math.radians(STEP_FLOOR_ROT_DEG), math.radians(cfg.max_jump_rotation_deg))
    tr = _bounded(sig.trans_m, STEP_FLOOR_TRANS_M, cfg.max_jump_translation_m)
    return np.diag([rot ** 2] * 3 + [tr ** 2] * 3)


def _bounded(sigma: float, floor: float, cap: float) -> float:
    """``sigma`` within [floor, cap]; the cap for NaN or infinity (nothing known: loose)."""
    if not math.isfinite(sigma):
        return max(cap, floor)
    return max(min(sigma, cap), floor)


def odometry_step_source(cov_a, cov_b, cfg, T_odom_a=None, T_odom_b=None) -> str:
    """Where the covariance of an odometry step between two keyframes comes from (``odometry_step_covariance``;
    ``a`` the earlier): the fixed sigmas, the growth of the pose covariance, the twist covariance (needs the two
    poses), or the drift figures."""
    if cfg.odom_covariance == 'fixed':
        return FIXED
    chain = [np.eye(4), np.eye(4)] if T_odom_a is None or T_odom_b is None else [T_odom_a, T_odom_b]
    return pose_uncertainty.odometry_sigma(chain, cov_a, cov_b, cfg.drift.cov_trans_per_m)[1]


def odometry_steps(window: Sequence[Hashable], odom: Mapping[Hashable, np.ndarray], cov: Mapping[Hashable, object],
                   cfg) -> Optional[OdometrySteps]:
    """The window's odometry factors as :func:`solve_window` builds them, summarised (:class:`OdometrySteps`);
    None for a window of one keyframe. ``cov``: per key what ``odometry_step_covariance`` takes."""
    if len(window) < 2:
        return None
    rot, tr, sources = [], [], []
    for a, b in zip(window[:-1], window[1:]):
        C = odometry_step_covariance(odom[a], odom[b], cov.get(a), cov.get(b), cfg)
        rot.append(math.sqrt(np.trace(C[:3, :3]) / 3.0))
        tr.append(math.sqrt(np.trace(C[3:, 3:]) / 3.0))
        sources.append(odometry_step_source(cov.get(a), cov.get(b), cfg, odom[a], odom[b]))
    return OdometrySteps(float(np.median(rot)), float(np.median(tr)), Counter(sources).most_common(1)[0][0])


def pose3_from_matrix(T_44: np.ndarray) -> gtsam.Pose3:
    """A gtsam Pose3 from a 4x4 matrix, its rotation re-orthonormalised."""
    T = np.asarray(T_44, dtype=np.float64)
    # Re-orthonormalise the rotation (odometry poses arrive with float rounding).
    U, _, Vt = np.linalg.svd(T[:3, :3])
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1.0, 1.0, -1.0]) @ Vt
    return gtsam.Pose3(gtsam.Rot3(R), gtsam.Point3(*T[:3, 3]))


def relative_pose(T_world_a: np.ndarray, T_world_b: np.ndarray) -> np.ndarray:
    """T_a_b = T_world_a^-1 T_world_b."""
    return np.linalg.inv(T_world_a) @ T_world_b


def solve_window(window: Sequence[Hashable], init: Mapping[Hashable, np.ndarray], odom: Mapping[Hashable, np.ndarray],
                 cov: Mapping[Hashable, object], anchor: Hashable, factors: Sequence = (),
                 kp_factors: Sequence = (), cfg=None, kp_huber_k: Optional[float] = None
                 ) -> Tuple[Dict[Hashable, np.ndarray], tuple]:
    """Optimise the window's poses: returns (``T_world_cam`` by key, (graph, result, index) for the marginals).

    window: the keys in time order; init: the starting poses; odom / cov: each keyframe's odometry pose and what
    the odometry says about itself there (``odometry_step_covariance``'s ``cov_a``, or None); anchor: the keyframe
    the gauge prior holds at its starting pose; factors: photometric ``(ref, src, T_ref_src, cov)``; kp_factors:
    keypoint or flow rotation ``(src, ref, T_src_ref, cov)``, Huber at ``kp_huber_k`` sigmas (None: the config's
    ``keypoint_huber_k``). Raises RuntimeError for a non-finite solution (gtsam raises it for an
    indeterminate system)."""
    idx = {k: i for i, k in enumerate(window)}
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for k in window:
        values.insert(idx[k], pose3_from_matrix(init[k]))
    prior_sigmas = np.array([math.radians(cfg.prior_sigma_rot_deg)] * 3 + [cfg.prior_sigma_trans_m] * 3)
    graph.add(gtsam.PriorFactorPose3(idx[anchor], pose3_from_matrix(init[anchor]),
                                     gtsam.noiseModel.Diagonal.Sigmas(prior_sigmas)))
    # Odometry between consecutive keyframes.
    for a, b in zip(window[:-1], window[1:]):
        T_ab = relative_pose(odom[a], odom[b])
        if cfg.odom_covariance == 'fixed':
            noise = gtsam.noiseModel.Diagonal.Sigmas(odometry_between_sigmas(T_ab, cfg))
        else:
            noise = gtsam.noiseModel.Gaussian.Covariance(odometry_step_covariance(
                odom[a], odom[b], cov.get(a), cov.get(b), cfg))
        graph.add(gtsam.BetweenFactorPose3(idx[a], idx[b], pose3_from_matrix(T_ab), noise))
    # Photometric alignments with their covariance, robustified.
    huber = gtsam.noiseModel.mEstimator.Huber.Create(cfg.photometric_huber_k)
    for r, s, T_ref_src, c in factors:
        if r not in idx or s not in idx:
            continue
        noise = gtsam.noiseModel.Robust.Create(huber, gtsam.noiseModel.Gaussian.Covariance(c))
        graph.add(gtsam.BetweenFactorPose3(idx[r], idx[s], pose3_from_matrix(T_ref_src), noise))
    # Keypoint relative poses (rotation and direction; length from the odometry), robustified.
    kp_huber = gtsam.noiseModel.mEstimator.Huber.Create(cfg.keypoint_huber_k if kp_huber_k is None else kp_huber_k)
    for s, r, T_src_ref, c in kp_factors:
        noise = gtsam.noiseModel.Robust.Create(kp_huber, gtsam.noiseModel.Gaussian.Covariance(c))
        graph.add(gtsam.BetweenFactorPose3(idx[s], idx[r], pose3_from_matrix(T_src_ref), noise))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(cfg.lm_max_iterations)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    out = {k: result.atPose3(idx[k]).matrix() for k in window}
    for k, T in out.items():
        if not np.all(np.isfinite(T)):
            raise RuntimeError(f'non-finite pose for keyframe {k}')
    return out, (graph, result, idx)


def relative_marginal_sigmas(solved: tuple, ref_key: Hashable, source_keys: Sequence[Hashable]
                             ) -> Dict[Hashable, pose_uncertainty.PoseSigma]:
    """Per source, per-axis stds of its pose relative to the reference from a solved graph's marginals
    (``solve_window``'s second value); {} when gtsam cannot compute them."""
    graph, result, idx = solved
    try:
        marg = gtsam.Marginals(graph, result)
    except RuntimeError:
        return {}
    out = {}
    r = idx[ref_key]
    for key in source_keys:
        j = idx[key]
        C = marg.jointMarginalCovariance([r, j]).fullMatrix()
        T_rs = result.atPose3(r).between(result.atPose3(j))
        J = np.hstack([-T_rs.inverse().AdjointMap(), np.eye(6)])   # d(T_r^-1 T_s) = -Ad(T_rs^-1) d_r + d_s
        Crel = J @ C @ J.T
        out[key] = pose_uncertainty.PoseSigma(rot_rad=math.sqrt(max(np.trace(Crel[:3, :3]) / 3, 0.0)),
                                              trans_m=math.sqrt(max(np.trace(Crel[3:, 3:]) / 3, 0.0)))
    return out
