"""The relative rotation of two views from dense optical flow, given the translation's direction (layer 2).

The window refiner's rotation evidence that does not depend on the depth being estimated. Plane-swept depth is
biased by the sweep's relative rotations much more than by its translations (``studies.pose_error_depth``), so
what the window needs from the images is the rotation; the odometry's translation direction is good to a few
degrees, far better than what two views of an indoor scene a few centimetres apart say about it.

1. :func:`flow_matches`: DIS optical flow (OpenCV) from view a to view b at the camera's own resolution, sampled on
   a grid where the image has texture (the smallest eigenvalue of the structure tensor above its median over the
   grid), optionally checked forward-backward. Thousands of sub-pixel correspondences where SIFT at the processing
   size finds a few dozen inliers; one flow costs about what SIFT detection and matching of one pair did.
2. :func:`rotation_given_direction`: the rotation ``R_b_a`` that minimises the correspondences' Sampson distances
   to the epipolar lines of ``(R_b_a, t_dir_b)`` with the direction held fixed (Gauss-Newton on the three rotation
   parameters from the odometry's rotation, re-selecting inliers by a shrinking threshold: trimmed least squares,
   so a moving object or a wrong flow vector is dropped, not averaged in). With the direction fixed the problem
   is well posed however small the baseline: only the component of a match across its epipolar line counts, and
   that is what a rotation error moves and a depth error does not. When the odometry has no translation at all
   the rotation is fitted to the matches' full displacement (a pure rotation maps them by ``K R K^-1``).
3. ``RotationEstimate.direction_ratio``: whether the held direction fits the images at all. The inliers' rms
   distance with it held over their rms once the direction is fitted too (5 dof, from the held solution): noise
   alone leaves this near 1 (two parameters more), a direction a degree or two off raises it well above. It is
   the evidence for trusting the images' rotation given the odometry's direction: where the camera's
   calibration, mount or timing does not match the odometry, the direction is off on every pair and the ratio's
   median stays high (the window refiner's ``rotation_evidence='auto'``). The inliers are those of the held fit,
   so a direction so far off that under half the matches fit it gives no estimate, not a ratio.

The covariance is the Gauss-Newton one, ``s^2 (J^T J)^-1`` with ``s`` the inliers' rms distance, times
``covariance_scale``: neighbouring flow vectors share their errors (the flow is smooth over patches), so the
inliers are far fewer independent measurements than their count says. ``studies.keypoint_accuracy --matcher
flow`` measures the scale on the rendered sequences (median NEES of the rotation against the ground truth, given
the true direction).

Conventions as in :mod:`dpv_sensor.core.keypoint_pose`: ``T_b_a`` maps points of view a into view b, rotations are
left increments about frame b's axes (radians), images are anything :func:`~dpv_sensor.core.keypoint_pose.to_gray_u8`
takes. No ROS, no torch.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Optional, Tuple

import cv2
import numpy as np

from dpv_sensor.core.keypoint_pose import refine_relative_pose, sampson_jacobian, sampson_px, to_gray_u8

__all__ = ['FlowConfig', 'FlowMatches', 'RotationEstimate', 'flow_matches', 'rotation_given_direction',
           'match_image']

_PRESETS = {'ultrafast': cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST, 'fast': cv2.DISOPTICAL_FLOW_PRESET_FAST,
            'medium': cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}


@dataclass(frozen=True)
class FlowConfig:
    """dis_preset: DIS optical flow preset ('ultrafast', 'fast', 'medium'); variational_iterations: DIS's
    variational refinement iterations per scale (None: the preset's 5, 40 % of its time; the default 0 skips it: the
    rotations on the refiner's pairs are as accurate, the direction ratio a little nearer 1);
    patch_stride: DIS's step between patches in pixels (None: the preset's; medium's 3); grid_px:
    spacing of the sampled pixels; texture_quantile: keep the grid pixels whose structure-tensor eigenvalue is
    above this quantile over the grid;
    forward_backward_px: > 0 also computes the flow back and drops pixels whose round trip misses by more (0: one
    flow; the trimmed fit drops wrong vectors); max_width: images wider than this are matched shrunk to it
    (``match_image``); inlier_px: the final inlier threshold on the Sampson distance (pixels); iterations:
    Gauss-Newton steps at most (fewer once a step is below converged_rad); min_inliers: fewer is no estimate;
    min_inlier_fraction: a smaller share of the matches agreeing is no estimate either (where the flow is wrong in
    many places, e.g. large displacements and occlusions, what agrees is not the scene's motion: on the rendered
    hospital pairs below a half the rotation errs by 0.5 degrees at the median, above 0.7 by 0.03); pixel_sigma:
    the smallest per-match std (pixels) the covariance assumes; covariance_scale: the covariance's factor for the
    matches' shared errors (module doc); direction_iterations / direction_stride: Gauss-Newton steps of the free
    fit that ``RotationEstimate.direction_ratio`` compares with, and the share of the inliers it uses (every n-th:
    the ratio is a statistic of the pair, not an estimate, and the fit is most of a pair's fitting time)."""
    dis_preset: str = 'medium'
    variational_iterations: Optional[int] = 0
    patch_stride: Optional[int] = None
    grid_px: int = 8
    texture_quantile: float = 0.5
    forward_backward_px: float = 0.0
    max_width: int = 640
    inlier_px: float = 0.5
    iterations: int = 8
    converged_rad: float = 1e-6
    min_inliers: int = 20
    min_inlier_fraction: float = 0.5
    pixel_sigma: float = 0.1
    covariance_scale: float = 52.0
    direction_iterations: int = 3
    direction_stride: int = 4

    def __post_init__(self):
        if self.dis_preset not in _PRESETS:
            raise ValueError(f'preset must be one of {sorted(_PRESETS)}, not {self.dis_preset!r}')
        if self.variational_iterations is not None and self.variational_iterations < 0:
            raise ValueError(f'variational_iterations must be >= 0 or None, not {self.variational_iterations}')
        if self.patch_stride is not None and self.patch_stride < 1:
            raise ValueError(f'patch_stride must be >= 1 or None, not {self.patch_stride}')


@dataclass
class FlowMatches:
    """Correspondences of view a's pixels ``pa_n2`` in view b ``pb_n2`` (pixels, float64) at the size ``K_33``
    belongs to; ``sampled`` grid pixels were looked at; ``flow_hw2``: the dense flow from a to b (float32, pixels)
    they were sampled from, which chains pairs into tracks (``stream.metric_anchors``)."""
    pa_n2: np.ndarray
    pb_n2: np.ndarray
    K_33: np.ndarray
    sampled: int = 0
    flow_hw2: Optional[np.ndarray] = None


@dataclass
class RotationEstimate:
    """ok: False when there is no estimate (reason says why, kind in a word: 'no_texture', 'disagree',
    'undetermined'); R_b_a: the rotation; cov_33: its covariance (rad^2, left increment about frame b's axes);
    inliers / matches: counts; rms_px: the inliers' rms distance; direction_ratio: that rms over the inliers' rms
    distance once the translation's direction is fitted too (5 dof from the held solution): near 1 where the given
    direction fits the images, above it where it does not (None without a translation)."""
    ok: bool
    reason: Optional[str] = None
    kind: str = 'ok'
    R_b_a: np.ndarray = None
    cov_33: Optional[np.ndarray] = None
    inliers: int = 0
    matches: int = 0
    rms_px: float = 0.0
    direction_ratio: Optional[float] = None

    def inverse(self) -> 'RotationEstimate':
        """The same estimate seen from view b: ``R_a_b`` and its covariance about frame a's axes (a left increment
        ``d`` on ``R_b_a`` is ``-R_b_a^T d`` on ``R_a_b``); counts, rms and ratio are the pair's."""
        if self.R_b_a is None:
            return dataclasses.replace(self)
        R = self.R_b_a
        cov = None if self.cov_33 is None else R.T @ self.cov_33 @ R
        return dataclasses.replace(self, R_b_a=R.T.copy(), cov_33=cov)


def match_image(image, K_33: np.ndarray, config: FlowConfig = FlowConfig()) -> Tuple[np.ndarray, np.ndarray]:
    """(grey uint8 image, its K) as :func:`flow_matches` takes them: shrunk to ``config.max_width`` when wider."""
    gray = to_gray_u8(image)
    K = np.asarray(K_33, np.float64).copy()
    h, w = gray.shape
    if w > config.max_width:
        s = config.max_width / w
        size = (config.max_width, max(2, int(round(h * s))))
        gray = cv2.resize(gray, size, interpolation=cv2.INTER_AREA)
        K[0] *= size[0] / w
        K[1] *= size[1] / h
    return gray, K


_DIS = {}


def _dis(config: FlowConfig):
    key = (config.dis_preset, config.variational_iterations, config.patch_stride)
    if key not in _DIS:
        dis = cv2.DISOpticalFlow_create(_PRESETS[config.dis_preset])
        if config.variational_iterations is not None:
            dis.setVariationalRefinementIterations(int(config.variational_iterations))
        if config.patch_stride is not None:
            dis.setPatchStride(int(config.patch_stride))
        _DIS[key] = dis
    return _DIS[key]


def flow_matches(gray_a: np.ndarray, gray_b: np.ndarray, K_33: np.ndarray,
                 config: FlowConfig = FlowConfig()) -> FlowMatches:
    """Textured grid pixels of grey image a and where the flow puts them in grey image b (same size, uint8)."""
    if gray_a.shape != gray_b.shape:
        raise ValueError(f'flow between images of different sizes: {gray_a.shape} and {gray_b.shape}')
    flow_ab = _dis(config).calc(gray_a, gray_b, None)
    h, w = gray_a.shape
    g = int(config.grid_px)
    ys, xs = np.mgrid[g // 2:h:g, g // 2:w:g]
    xs, ys = xs.ravel(), ys.ravel()
    texture = cv2.cornerMinEigenVal(gray_a, 5)[ys, xs]
    f = flow_ab[ys, xs].astype(np.float64)
    xb, yb = xs + f[:, 0], ys + f[:, 1]
    keep = (texture > np.quantile(texture, config.texture_quantile)) & (xb >= 0) & (xb <= w - 1) & \
        (yb >= 0) & (yb <= h - 1)
    if config.forward_backward_px > 0:
        flow_ba = _dis(config).calc(gray_b, gray_a, None)
        keep &= round_trip_px(flow_ba, np.c_[xs, ys], np.c_[xb, yb]) < config.forward_backward_px
    pa = np.c_[xs, ys][keep].astype(np.float64)
    return FlowMatches(pa, np.c_[xb, yb][keep], np.asarray(K_33, np.float64), sampled=len(xs), flow_hw2=flow_ab)


def dense_flow(gray_a: np.ndarray, gray_b: np.ndarray, config: FlowConfig = FlowConfig()) -> np.ndarray:
    """DIS optical flow from grey image a to grey image b (h, w, 2), float32 pixels, with the config's preset."""
    return _dis(config).calc(gray_a, gray_b, None)


def round_trip_px(flow_ba_hw2: np.ndarray, pa_n2: np.ndarray, pb_n2: np.ndarray) -> np.ndarray:
    """How far (pixels) the flow back from b to a, read at each match's pixel in b, misses its pixel in a."""
    pb = np.asarray(pb_n2, np.float64)
    back = cv2.remap(flow_ba_hw2, pb[:, 0].astype(np.float32)[None], pb[:, 1].astype(np.float32)[None],
                     cv2.INTER_LINEAR)[0].astype(np.float64)
    miss = pb + back - np.asarray(pa_n2, np.float64)
    return np.hypot(miss[:, 0], miss[:, 1])


def _rotate(R: np.ndarray, w: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(w, np.float64).reshape(3, 1))[0] @ R


def _rotation_px(xa: np.ndarray, xb: np.ndarray, R: np.ndarray, t, f: float) -> np.ndarray:
    """Per match the x and y displacement (pixels) between b's point and a's rotated by ``R`` (no translation)."""
    p = xa @ R.T
    return (f * (p[:, :2] / p[:, 2:3] - xb[:, :2] / xb[:, 2:3])).ravel()


def _rotation_px_jacobian(xa: np.ndarray, xb: np.ndarray, R: np.ndarray, t, f: float
                          ) -> Tuple[np.ndarray, np.ndarray]:
    """:func:`_rotation_px` and its Jacobian (2n, 3) with respect to a left rotation increment (``p = R xa`` moves
    by ``d x p``)."""
    p = xa @ R.T
    z = np.zeros(len(p))
    dp = np.stack([np.c_[z, p[:, 2], -p[:, 1]], np.c_[-p[:, 2], z, p[:, 0]], np.c_[p[:, 1], -p[:, 0], z]], 1)
    J = (dp[:, :2] * p[:, 2, None, None] - p[:, :2, None] * dp[:, 2:3]) / (p[:, 2] ** 2)[:, None, None]
    return _rotation_px(xa, xb, R, t, f), f * J.reshape(-1, 3)


def rotation_given_direction(matches: FlowMatches, t_dir_b: np.ndarray, R0_b_a: np.ndarray,
                             config: FlowConfig = FlowConfig(), direction_ratio: bool = True) -> RotationEstimate:
    """The rotation ``R_b_a`` of the matches given the translation direction ``t_dir_b`` (of ``t_b_a``; a zero
    vector: no translation), from the start ``R0_b_a`` (module doc). ``direction_ratio``: also measure
    :attr:`RotationEstimate.direction_ratio` (with a translation)."""
    n = len(matches.pa_n2)
    if n < config.min_inliers:
        return RotationEstimate(False, f'too few textured flow matches ({n} < {config.min_inliers})',
                                'no_texture', matches=n)
    K = matches.K_33
    Kinv = np.linalg.inv(K)
    xa = np.c_[matches.pa_n2, np.ones(n)] @ Kinv.T
    xb = np.c_[matches.pb_n2, np.ones(n)] @ Kinv.T
    f = 0.5 * (K[0, 0] + K[1, 1])
    t = np.asarray(t_dir_b, np.float64).ravel()
    norm = float(np.linalg.norm(t))
    if norm > 1e-9:
        t, linearised, per_match = t / norm, sampson_jacobian, 1
    else:
        linearised, per_match = _rotation_px_jacobian, 2

    def distances(r: np.ndarray) -> np.ndarray:
        return np.abs(r).reshape(-1, per_match).max(axis=1)

    def inliers(dist: np.ndarray, threshold_px: float) -> Tuple[np.ndarray, np.ndarray]:
        """(per match: within the threshold, per residual row: the same)."""
        sel = dist < threshold_px
        return sel, np.repeat(sel, per_match)

    R = np.asarray(R0_b_a, np.float64).copy()
    JtJ = None
    for _ in range(config.iterations):
        r, J = linearised(xa, xb, R, t, f)
        dist = distances(r)
        sel, rows = inliers(dist, max(config.inlier_px, 2.5 * float(np.median(dist))))
        if sel.sum() < config.min_inliers:
            break
        J = J[rows]
        JtJ = J.T @ J
        step = np.linalg.lstsq(JtJ, -J.T @ r[rows], rcond=None)[0]
        R = _rotate(R, step)
        if float(np.linalg.norm(step)) < config.converged_rad:
            break
    r, J = linearised(xa, xb, R, t, f)
    sel, rows = inliers(distances(r), config.inlier_px)
    n_in = int(sel.sum())
    if JtJ is None or n_in < config.min_inliers:
        return RotationEstimate(False, f'too few flow matches agree on a rotation ({n_in} < {config.min_inliers})',
                                'disagree', inliers=n_in, matches=n)
    if n_in < config.min_inlier_fraction * n:
        return RotationEstimate(False, f'only {n_in} of {n} flow matches agree on a rotation (less than '
                                       f'{config.min_inlier_fraction:g})', 'disagree', inliers=n_in, matches=n)
    r_in, J = r[rows], J[rows]
    rms = float(np.sqrt(np.mean(r_in ** 2)))
    info = J.T @ J
    if not np.all(np.isfinite(info)) or np.linalg.cond(info) > 1e12:
        return RotationEstimate(False, 'the flow matches do not determine the rotation', 'undetermined',
                                inliers=n_in, matches=n)
    cov = max(config.pixel_sigma, rms) ** 2 * np.linalg.inv(info) * config.covariance_scale
    if not math.isfinite(float(np.trace(cov))):
        return RotationEstimate(False, 'non-finite rotation covariance', 'undetermined', inliers=n_in, matches=n)
    ratio = _direction_ratio(xa[sel], xb[sel], R, t, f, config) if per_match == 1 and direction_ratio else None
    return RotationEstimate(True, None, 'ok', R, 0.5 * (cov + cov.T), n_in, n, rms, ratio)


def _direction_ratio(xa: np.ndarray, xb: np.ndarray, R: np.ndarray, t: np.ndarray, f: float,
                     config: FlowConfig) -> float:
    """The inliers' rms distance with the direction held over the same once rotation and direction are both fitted
    (:attr:`RotationEstimate.direction_ratio`), on every ``direction_stride``-th inlier."""
    xa, xb = xa[::max(1, config.direction_stride)], xb[::max(1, config.direction_stride)]
    rms_held = float(np.sqrt(np.mean(sampson_px(xa, xb, R, t, f) ** 2)))
    R5, t5 = refine_relative_pose(xa, xb, R, t, f, 0.0, iterations=config.direction_iterations)[:2]
    rms_free = float(np.sqrt(np.mean(sampson_px(xa, xb, R5, t5, f) ** 2)))
    return rms_held / rms_free if rms_free > 0.0 else math.inf
