"""Relative pose of two views from matched keypoints: rotation and translation direction, with a covariance.

Image evidence on the pose that does not depend on any depth estimate: SIFT (or ORB) keypoints of both images,
nearest-neighbour matching with Lowe's ratio test, RANSAC on the essential matrix and the cheirality test of
``cv2.recoverPose``. Monocular matches fix the rotation and the direction of the translation, not its length.

Convention: for views ``a`` and ``b`` with intrinsics ``K``, the result is ``T_b_a`` (points in ``a``'s camera
frame to ``b``'s): ``R_b_a`` and the unit direction ``t_dir_b`` of ``t_b_a``.

Covariance: after RANSAC, rotation and direction are refined by Gauss-Newton on the Sampson distances of the
inliers (pixels), and their covariance is ``s^2 (J^T J)^-1`` with ``J`` the Jacobian of those distances with
respect to a left rotation increment (3) and a direction increment (2, in the plane normal to the direction), and
``s`` the larger of ``pixel_sigma`` and the distances' rms. Near-degenerate pairs (small parallax) couple rotation
and translation direction; the covariance then says so (large, correlated), where an isotropic model would not.
:func:`keypoint_covariance` is the isotropic figure for ``n`` well-spread inliers (``pixel_sigma / (f sqrt(n))``
rad about each axis, ``pixel_sigma / (p sqrt(n))`` for the direction at median parallax ``p``), a lower bound.

Fewer inliers give a larger covariance (``1 / n``). numpy, OpenCV and torch (the matcher's matrix product); no ROS.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional, Tuple

import cv2
import numpy as np
import torch

__all__ = ['KeypointConfig', 'KeypointPose', 'Features', 'detect_features', 'keypoint_relative_pose',
           'keypoint_covariance', 'rotation_given_direction_gain', 'rotation_factor_covariance_gtsam',
           'to_gray_u8', 'sampson_px', 'sampson_jacobian', 'refine_relative_pose']


@dataclass
class KeypointConfig:
    """detector: 'sift' or 'orb'; max_features: keypoints per image; ratio: Lowe's ratio test; ransac_px: the
    essential matrix's RANSAC threshold (pixels); ransac_confidence: its confidence; min_inliers: fewer inliers than
    this is no estimate (``ok`` False); pixel_sigma: the std of a keypoint's position (pixels) for the covariance;
    min_parallax_px: a median parallax below this gives no translation direction (``t_dir_b`` None);
    rotation_floor_deg, direction_floor_deg: added in quadrature to each axis of the inliers' covariance, for errors
    the Sampson spread does not see (measured by ``studies.keypoint_accuracy``; 0 by default)."""
    detector: str = 'sift'
    max_features: int = 1000
    ratio: float = 0.8
    ransac_px: float = 1.0
    ransac_confidence: float = 0.999
    min_inliers: int = 20
    pixel_sigma: float = 1.0
    min_parallax_px: float = 1.0
    rotation_floor_deg: float = 0.0
    direction_floor_deg: float = 0.0


@dataclass
class KeypointPose:
    """The keypoint estimate of ``T_b_a``.

    ok: False when there is no estimate (reason says why); R_b_a: rotation (3x3); t_dir_b: unit direction of
    ``t_b_a`` (None when the parallax is too small to give one); inliers / matches: counts after RANSAC and the
    cheirality test / after the ratio test; parallax_px: median de-rotated displacement of the inliers;
    sigma_rot_rad, sigma_dir_rad: per-axis stds (module doc).
    """
    ok: bool
    reason: Optional[str] = None
    R_b_a: np.ndarray = field(default_factory=lambda: np.eye(3))
    t_dir_b: Optional[np.ndarray] = None
    inliers: int = 0
    matches: int = 0
    parallax_px: float = 0.0
    sigma_rot_rad: float = math.inf
    sigma_dir_rad: float = math.inf
    cov_55: Optional[np.ndarray] = None      # (left rotation increment, direction increment in basis_32)
    basis_32: Optional[np.ndarray] = None    # two unit vectors normal to t_dir_b
    residual_px: float = 0.0                 # rms Sampson distance of the inliers
    pa_n2: Optional[np.ndarray] = None       # the inliers' pixels in view a and in view b
    pb_n2: Optional[np.ndarray] = None

    def rotation_covariance(self) -> np.ndarray:
        """3x3 covariance of the rotation (rad^2) about the axes of frame b."""
        if self.cov_55 is not None:
            return self.cov_55[:3, :3].copy()
        return np.eye(3) * self.sigma_rot_rad ** 2

    def between_covariance_gtsam(self, baseline_m: float, scale_sigma_rel: float) -> np.ndarray:
        """6x6 covariance (gtsam order: rotation, translation) of a Pose3 between factor ``T_b_a`` whose translation
        is ``baseline_m * t_dir_b``: the direction's std across the baseline, ``scale_sigma_rel * baseline_m``
        along it (the length is not measured by the images; it is the odometry's)."""
        along = (scale_sigma_rel * baseline_m) ** 2
        cov = np.zeros((6, 6))
        if self.cov_55 is not None and self.t_dir_b is not None:
            J = np.zeros((6, 5))                 # (rotation, translation) in frame b from the 5 parameters
            J[:3, :3] = np.eye(3)
            J[3:, 3:] = baseline_m * self.basis_32
            cov = J @ self.cov_55 @ J.T
            t = np.asarray(self.t_dir_b, np.float64)
            cov[3:, 3:] += along * np.outer(t, t)
        else:
            cov[:3, :3] = self.rotation_covariance()
            cov[3:, 3:] = np.eye(3) * max(along, 1e6 if self.t_dir_b is None else along)
        return _gtsam_tangent(cov, self.R_b_a)

    def rotation_given_direction(self, t_dir_b: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """(R_b_a, 3x3 covariance about frame b's axes) of the rotation given the translation direction
        ``t_dir_b`` from elsewhere (the odometry's): the linear conditional of the 5-dof estimate,
        ``exp(-G e) R`` with ``e = B^T (t_dir - t_dir_b)`` the direction's offset and ``G = S_rd S_dd^-1``, and
        covariance ``S_rr - G S_dr``. Rotation and direction are correlated (a turn and a sideways step move
        the matches alike), so a well-known direction sharpens the rotation. The rotation alone (its marginal)
        where there is no direction or the two directions are more than 30 degrees apart."""
        u = np.asarray(t_dir_b, np.float64).ravel()
        u = u / max(float(np.linalg.norm(u)), 1e-12)
        if self.cov_55 is None or self.t_dir_b is None or float(u @ self.t_dir_b) < math.cos(math.radians(30.0)):
            return np.asarray(self.R_b_a, np.float64).copy(), self.rotation_covariance()
        G, cov = rotation_given_direction_gain(self.cov_55)
        shift = -G @ (self.basis_32.T @ (np.asarray(self.t_dir_b, np.float64) - u))
        R = cv2.Rodrigues(shift.reshape(3, 1))[0] @ np.asarray(self.R_b_a, np.float64)
        return R, cov

    def rotation_covariance_gtsam(self, cov_33: np.ndarray, free_translation_var: float) -> np.ndarray:
        """6x6 covariance (gtsam order) of a Pose3 between factor ``T_b_a`` that holds only a rotation with
        covariance ``cov_33`` (frame b's axes): the translation gets ``free_translation_var`` on each axis, so
        it is left to the other factors."""
        return rotation_factor_covariance_gtsam(cov_33, self.R_b_a, free_translation_var)


def rotation_factor_covariance_gtsam(cov_33: np.ndarray, R_b_a: np.ndarray, free_translation_var: float
                                     ) -> np.ndarray:
    """6x6 covariance (gtsam order) of a Pose3 between factor ``T_b_a`` with rotation ``R_b_a`` that holds only
    the rotation, with covariance ``cov_33`` about frame b's axes: the translation gets ``free_translation_var`` on
    each axis, so it is left to the other factors."""
    cov = np.zeros((6, 6))
    cov[:3, :3] = cov_33
    cov[3:, 3:] = np.eye(3) * free_translation_var
    return _gtsam_tangent(cov, R_b_a)


def rotation_given_direction_gain(cov_55: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """(G 3x2, conditional covariance 3x3) of a (rotation 3, direction 2) estimate with covariance ``cov_55``:
    given the direction's offset ``e`` the rotation moves by ``-G e``, ``G = S_rd S_dd^-1``, and its covariance is
    ``S_rr - G S_dr`` (the linear-Gaussian conditional)."""
    S = np.asarray(cov_55, np.float64)
    G = S[:3, 3:] @ np.linalg.pinv(S[3:, 3:])
    cov = S[:3, :3] - G @ S[3:, :3]
    return G, 0.5 * (cov + cov.T)


def _gtsam_tangent(cov_66: np.ndarray, R_b_a: np.ndarray) -> np.ndarray:
    """A covariance of (rotation, translation) increments about frame b's axes in gtsam's tangent of ``T_b_a``,
    which is on the right: increments in frame a's axes (``R^T``)."""
    Rt = np.asarray(R_b_a, np.float64).T
    A = np.zeros((6, 6))
    A[:3, :3] = Rt
    A[3:, 3:] = Rt
    return A @ cov_66 @ A.T


def keypoint_covariance(n_inliers: int, focal_px: float, parallax_px: float, pixel_sigma: float = 1.0
                        ) -> Tuple[float, float]:
    """(sigma_rot_rad, sigma_dir_rad) for ``n_inliers`` matches (module doc); inf for no inliers."""
    if n_inliers <= 0:
        return math.inf, math.inf
    root = math.sqrt(n_inliers)
    s_rot = pixel_sigma / (focal_px * root)
    s_dir = pixel_sigma / (parallax_px * root) if parallax_px > 0 else math.inf
    return s_rot, s_dir


def to_gray_u8(image) -> np.ndarray:
    """uint8 HxW grey from uint8 / float [0, 1] HxW(x3) or a (3, H, W) / (1, 3, H, W) tensor."""
    a = image.detach().cpu().numpy() if hasattr(image, 'detach') else np.asarray(image)
    if a.ndim == 4:
        a = a[0]
    if a.ndim == 3 and a.shape[0] in (1, 3) and a.shape[-1] not in (1, 3):
        a = np.moveaxis(a, 0, -1)
    if a.dtype != np.uint8:
        a = np.clip(np.asarray(a, np.float32) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    if a.ndim == 3:
        a = cv2.cvtColor(a, cv2.COLOR_RGB2GRAY) if a.shape[2] == 3 else a[..., 0]
    return np.ascontiguousarray(a)


@dataclass
class Features:
    """The keypoints and descriptors of one image (``detect_features``), to match it against several others without
    detecting again (a window keyframe is matched as the reference and later as a source)."""
    keypoints: tuple
    descriptors: Optional[np.ndarray]
    detector: str
    points_n2: Optional[np.ndarray] = field(default=None, repr=False)

    def points(self) -> np.ndarray:
        """(N, 2) float64 pixel positions of the keypoints (computed once)."""
        if self.points_n2 is None:
            self.points_n2 = np.float64([k.pt for k in self.keypoints]).reshape(-1, 2)
        return self.points_n2


def detect_features(image, config: Optional[KeypointConfig] = None) -> Features:
    """Keypoints and descriptors of an image (any form :func:`to_gray_u8` takes) with the configured detector."""
    cfg = config or KeypointConfig()
    if cfg.detector == 'sift':
        det = cv2.SIFT_create(nfeatures=cfg.max_features)
    elif cfg.detector == 'orb':
        det = cv2.ORB_create(nfeatures=cfg.max_features)
    else:
        raise ValueError(f"detector must be 'sift' or 'orb', not {cfg.detector!r}")
    kp, desc = det.detectAndCompute(to_gray_u8(image), None)
    return Features(tuple(kp or ()), desc, cfg.detector)


def _features(image_or_features, cfg: KeypointConfig) -> Features:
    if isinstance(image_or_features, Features):
        if image_or_features.detector != cfg.detector:
            raise ValueError(f'features from {image_or_features.detector!r}, matching with {cfg.detector!r}')
        return image_or_features
    return detect_features(image_or_features, cfg)


def _match(desc_a, desc_b, cfg: KeypointConfig) -> Tuple[np.ndarray, np.ndarray]:
    """Indices (into a, into b) of the nearest neighbours in b of a's descriptors that pass Lowe's ratio test."""
    if cfg.detector == 'sift':
        return _match_l2(desc_a, desc_b, cfg.ratio)
    pairs = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(desc_a, desc_b, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < cfg.ratio * p[1].distance]
    return (np.array([m.queryIdx for m in good], np.int64).reshape(-1),
            np.array([m.trainIdx for m in good], np.int64).reshape(-1))


def _match_l2(desc_a: np.ndarray, desc_b: np.ndarray, ratio: float) -> Tuple[np.ndarray, np.ndarray]:
    """Brute-force two nearest neighbours in L2 by one matrix product: ``|a|^2 + |b|^2 - 2 a.b``.

    The same matches as OpenCV's brute-force ``knnMatch`` with ``NORM_L2``, several times faster beside the
    networks: SIFT descriptors hold whole numbers (0..255), so every product and sum here is an integer below
    2^24 and float32 holds it exactly; the square roots are then OpenCV's distances to the bit, and the ratio
    test compares them in float64 as the DMatch distances were."""
    a = torch.from_numpy(np.ascontiguousarray(desc_a, np.float32))
    b = torch.from_numpy(np.ascontiguousarray(desc_b, np.float32))
    if len(b) < 2 or len(a) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    with torch.no_grad():
        d2_ab = (a * a).sum(1, keepdim=True) + (b * b).sum(1)[None] - 2.0 * (a @ b.T)
        best2_d2, best2_idx = torch.topk(d2_ab, 2, dim=1, largest=False, sorted=True)
        dist_a2 = best2_d2.clamp_min(0.0).sqrt().double()
    keep = (dist_a2[:, 0] < ratio * dist_a2[:, 1]).numpy()
    return np.flatnonzero(keep).astype(np.int64), best2_idx[:, 0].numpy()[keep].astype(np.int64)


def keypoint_relative_pose(image_a, image_b, K_33: np.ndarray, config: Optional[KeypointConfig] = None,
                           T_b_a_prior_44: Optional[np.ndarray] = None, prior_gate_px: float = 0.0) -> KeypointPose:
    """``T_b_a`` from matched keypoints of two views with the same intrinsics ``K_33`` (module doc). Each view is
    an image or its :class:`Features` (detected once, matched many times).

    ``T_b_a_prior_44`` with ``prior_gate_px > 0``: before RANSAC, drop matches whose Sampson distance under the
    prior (e.g. the odometry) exceeds the gate. Repetitive texture (tiles, checkers) gives ratio-test matches one
    period off that agree with each other on a wrong motion; the gate removes them without fixing the estimate
    to the prior (it should be several times the shift the prior's error can cause)."""
    cfg = config or KeypointConfig()
    K = np.asarray(K_33, np.float64)
    fa, fb = _features(image_a, cfg), _features(image_b, cfg)
    kp_a, d_a, kp_b, d_b = fa.keypoints, fa.descriptors, fb.keypoints, fb.descriptors
    if d_a is None or d_b is None or len(kp_a) < cfg.min_inliers or len(kp_b) < cfg.min_inliers:
        n = min(len(kp_a), len(kp_b))
        return KeypointPose(False, f'too few keypoints ({n} < {cfg.min_inliers})')
    idx_a, idx_b = _match(d_a, d_b, cfg)
    n_good = len(idx_a)
    if n_good < cfg.min_inliers:
        return KeypointPose(False, f'too few matches after the ratio test ({n_good} < {cfg.min_inliers})',
                            matches=n_good)
    pa = fa.points()[idx_a]
    pb = fb.points()[idx_b]
    if T_b_a_prior_44 is not None and prior_gate_px > 0:
        T0 = np.asarray(T_b_a_prior_44, np.float64)
        t0 = T0[:3, 3] / max(float(np.linalg.norm(T0[:3, 3])), 1e-12)
        keep = np.abs(sampson_px(_normalised(pa, K), _normalised(pb, K), T0[:3, :3], t0, K[0, 0])) <= prior_gate_px
        pa, pb = pa[keep], pb[keep]
        if len(pa) < cfg.min_inliers:
            return KeypointPose(False, f'too few matches agree with the prior ({len(pa)} < {cfg.min_inliers})',
                                matches=len(pa))
    return relative_pose_from_points(pa, pb, K, cfg, n_good)


def relative_pose_from_points(pa: np.ndarray, pb: np.ndarray, K_33: np.ndarray, config: Optional[KeypointConfig] = None,
                              n_matches: Optional[int] = None) -> KeypointPose:
    """``T_b_a`` from matched pixels ``pa`` (view a) and ``pb`` (view b), (n, 2) each, with the intrinsics ``K_33``:
    the essential matrix by RANSAC, the cheirality test, and the inliers' refinement and covariance (module doc).
    ``n_matches``: the matches counted before (default: n)."""
    cfg = config or KeypointConfig()
    K = np.asarray(K_33, np.float64)
    pa, pb = np.ascontiguousarray(pa), np.ascontiguousarray(pb)
    n_good = len(pa) if n_matches is None else int(n_matches)
    if len(pa) < max(cfg.min_inliers, 5):
        return KeypointPose(False, f'too few matches ({len(pa)} < {cfg.min_inliers})', matches=n_good)
    E, mask = cv2.findEssentialMat(pa, pb, K, method=cv2.RANSAC, prob=cfg.ransac_confidence, threshold=cfg.ransac_px)
    if E is None or E.shape != (3, 3):
        return KeypointPose(False, 'no essential matrix', matches=n_good)
    n_in, R, t, mask = cv2.recoverPose(E, pa, pb, K, mask=mask)
    n_in = int(n_in)
    if n_in < cfg.min_inliers:
        return KeypointPose(False, f'too few inliers ({n_in} < {cfg.min_inliers})', inliers=n_in,
                            matches=n_good)
    sel = mask.ravel() > 0
    parallax = _derotated_parallax(pa[sel], pb[sel], K, R)
    f = 0.5 * (K[0, 0] + K[1, 1])
    s_rot, s_dir = keypoint_covariance(n_in, f, parallax, cfg.pixel_sigma)
    R = np.asarray(R, np.float64)
    t_dir = np.asarray(t, np.float64).ravel()
    t_dir = t_dir / np.linalg.norm(t_dir)
    xa = _normalised(pa[sel], K)
    xb = _normalised(pb[sel], K)
    R, t_dir, cov, B, rms = refine_relative_pose(xa, xb, R, t_dir, f, cfg.pixel_sigma)
    cov = cov + np.diag(np.radians([cfg.rotation_floor_deg] * 3 + [cfg.direction_floor_deg] * 2)) ** 2
    if parallax < cfg.min_parallax_px:
        s_rot = math.hypot(s_rot, math.radians(cfg.rotation_floor_deg))
        return KeypointPose(True, None, R, None, n_in, n_good, parallax, s_rot, math.inf, residual_px=rms,
                            pa_n2=pa[sel], pb_n2=pb[sel])
    s_rot = math.sqrt(max(np.linalg.eigvalsh(cov[:3, :3])[-1], s_rot ** 2))
    s_dir = math.sqrt(max(np.linalg.eigvalsh(cov[3:, 3:])[-1], s_dir ** 2))
    return KeypointPose(True, None, R, t_dir, n_in, n_good, parallax, s_rot, s_dir, cov, B, rms, pa[sel], pb[sel])


def _normalised(p: np.ndarray, K: np.ndarray) -> np.ndarray:
    return np.c_[p, np.ones(len(p))] @ np.linalg.inv(K).T


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _basis(t: np.ndarray) -> np.ndarray:
    """Two unit vectors normal to ``t`` (3x2)."""
    a = np.eye(3)[int(np.argmin(np.abs(t)))]
    u = np.cross(t, a)
    u /= np.linalg.norm(u)
    return np.c_[u, np.cross(t, u)]


def _apply(R: np.ndarray, t: np.ndarray, B: np.ndarray, d: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    R2 = cv2.Rodrigues(d[:3].reshape(3, 1))[0] @ R
    t2 = t + B @ d[3:]
    return R2, t2 / np.linalg.norm(t2)


def sampson_px(xa: np.ndarray, xb: np.ndarray, R: np.ndarray, t: np.ndarray, f: float) -> np.ndarray:
    """Sampson distances (pixels at focal ``f``) of normalised matches to the epipolar geometry ``E = [t]x R``."""
    E = _skew(t) @ R
    Ea = xa @ E.T
    Eb = xb @ E
    num = np.sum(xb * Ea, axis=1)
    den = np.sqrt(Ea[:, 0] ** 2 + Ea[:, 1] ** 2 + Eb[:, 0] ** 2 + Eb[:, 1] ** 2) + 1e-15
    return f * num / den


def sampson_jacobian(xa: np.ndarray, xb: np.ndarray, R: np.ndarray, t: np.ndarray, f: float,
                     B_32: Optional[np.ndarray] = None) -> Tuple[np.ndarray, np.ndarray]:
    """:func:`sampson_px` and its Jacobian (n, 3) with respect to a left rotation increment ``R <- exp([d]x) R``,
    or (n, 5) with the translation's direction moved in the plane of ``B_32`` too (``t <- t + B d``, to first order
    the normalised direction's move as well, ``B`` being normal to ``t``).

    With ``u = R xa`` and ``w = xb x t`` the distance is ``f u.w / |(Ea_0, Ea_1, Eb_0, Eb_1)|`` for the epipolar
    lines ``Ea = t x u`` (in b) and ``Eb = R^T w`` (in a); a rotation increment moves ``u`` by ``d x u`` and ``w``'s
    image in a by ``R^T (w x d)``, a direction increment moves ``t``."""
    u = xa @ R.T
    St = _skew(t)
    w = xb @ St                                         # xb x t
    Ea = u @ St.T                                       # t x u
    Eb = w @ R
    num = np.sum(u * w, axis=1)
    den = np.sqrt(Ea[:, 0] ** 2 + Ea[:, 1] ** 2 + Eb[:, 0] ** 2 + Eb[:, 1] ** 2) + 1e-15
    r = f * num / den

    def chain(dnum, dEa0, dEa1, dEb0, dEb1):
        dden = (Ea[:, :1] * dEa0 + Ea[:, 1:2] * dEa1 + Eb[:, :1] * dEb0 + Eb[:, 1:2] * dEb1) / den[:, None]
        return f * (dnum / den[:, None] - (num / den ** 2)[:, None] * dden)

    tu = u @ t
    dEa0, dEa1 = -u[:, :1] * t, -u[:, 1:2] * t          # d(t x (d x u)) = ((t.u) I - u t^T) d, rows 0 and 1
    dEa0[:, 0] += tu
    dEa1[:, 1] += tu
    # R[:, i] x w, row-wise: w @ [R[:, i]]x^T
    J = chain(_cross_rows(u, w), dEa0, dEa1, w @ _skew(R[:, 0]).T, w @ _skew(R[:, 1]).T)
    if B_32 is not None:
        z = np.zeros(len(u))
        Jt = chain(_cross_rows(u, xb), np.c_[z, u[:, 2], -u[:, 1]], np.c_[-u[:, 2], z, u[:, 0]],
                   xb @ _skew(R[:, 0]).T, xb @ _skew(R[:, 1]).T)
        J = np.c_[J, Jt @ B_32]
    return r, J


def _cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross products of two (n, 3) arrays."""
    return np.c_[a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                 a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]]


def refine_relative_pose(xa, xb, R, t, f, pixel_sigma, iterations: int = 5):
    """Gauss-Newton on the Sampson distances of normalised matches over the rotation and the translation's direction
    (5 dof) from ``(R, t)``; returns (R, t, 5x5 covariance, basis, rms px)."""
    for it in range(iterations + 1):
        B = _basis(t)
        r0, J = sampson_jacobian(xa, xb, R, t, f, B)
        JtJ = J.T @ J
        if it == iterations:
            break
        step = np.linalg.lstsq(JtJ, -J.T @ r0, rcond=None)[0]
        R_new, t_new = _apply(R, t, B, step)
        if np.sum(sampson_px(xa, xb, R_new, t_new, f) ** 2) >= np.sum(r0 ** 2):
            break
        R, t = R_new, t_new
    n = len(r0)
    rms = float(np.sqrt(np.sum(r0 ** 2) / max(n - 5, 1)))
    s = max(pixel_sigma, rms)
    cov = s ** 2 * np.linalg.pinv(JtJ)
    return R, t, cov, B, rms


def _derotated_parallax(pa: np.ndarray, pb: np.ndarray, K: np.ndarray, R_b_a: np.ndarray) -> float:
    """Median displacement (pixels) of the matches after mapping ``a``'s points through the rotation only."""
    H = K @ R_b_a @ np.linalg.inv(K)
    ph = np.c_[pa, np.ones(len(pa))] @ H.T
    pr = ph[:, :2] / ph[:, 2:3]
    return float(np.median(np.linalg.norm(pb - pr, axis=1))) if len(pa) else 0.0
