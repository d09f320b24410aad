"""Direct (photometric) alignment of a source image to a reference image with known reference depth.

This is the inner solver of the pose refinement of paper sec. 3.4, eq. 11:

    min_{dT}  sum_u  C(u) * rho( I_ref(u) - (a * I_src(warp(u; d(u), T_src_ref)) + b) )

- ``d``, ``C``: depth and confidence of the reference view (the filter's predicted DPV, eq. 1/2); pixels
  without depth (``<= 0`` or non-finite) are ignored and C scales each pixel's weight.
- ``rho``: Huber norm (the paper's L1, made differentiable near zero), threshold ``huber_k`` times a robust
  (MAD) estimate of the residual scale that is re-estimated at every accepted step; residuals beyond
  ``outlier_k`` scales are rejected (occlusions, specularities). Only the strongest-gradient pixel of each cell of
  a grid is used (about ``max_pixels`` per level, spread over the image).
- Optionally a per-pixel inverse-depth std (from the DPV confidence) down-weights pixels by how much their
  depth uncertainty moves their residual.
- ``a, b``: affine brightness of the pair (exposure / gain changes), estimated jointly (optional).
- Forward-compositional Levenberg-Marquardt on SE(3): ``T_src_ref <- exp(xi) T_src_ref`` with the twist
  ``xi = (rho, omega)`` (translation first, the map of ``geometry.se3_exp``), on an image pyramid, coarse to
  fine.
  The source image and its gradients are warped as :func:`dpv_sensor.core.geometry.warp_image_with_depth` does, but
  evaluated only at the selected pixels (:func:`_sample_source`, tested against it).

The result carries the 6x6 covariance of ``xi`` at the solution: ``s^2 H^-1`` marginalised over the brightness
parameters (``H`` the Gauss-Newton Hessian of the finest level, ``s^2`` the weighted residual variance), times
``covariance_inflation`` because neighbouring pixels' noise is strongly correlated (interpolation, blur, pyramid),
which the i.i.d. formula ignores, and the solution's sensitivities to a global depth scale / inverse-depth offset
error. :meth:`AlignmentResult.between_covariance_gtsam` gives the covariance in the ordering gtsam's
``BetweenFactorPose3`` expects, widened by those global depth errors.

Everything is torch (float32 images by default; the normal equations are solved in float64); inputs may be
numpy arrays or tensors. No ROS import.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import List, Optional, Tuple

import gtsam
import numpy as np
import torch
import torch.nn.functional as F

from dpv_sensor.core.geometry import (BOUNDS_TOL, Z_EPS, backproject, camera_grid_affine, camera_resample_grid, project,
                                      scale_intrinsics, transform_points)
from dpv_sensor.core.pose_math import relative_pose_error_np

__all__ = ['AlignmentConfig', 'AlignmentResult', 'Aligner', 'ImagePyramid', 'align_photometric', 'to_gray',
           'resample_map', 'pose_error', 'twist_to_gtsam_order', 'inverse_depth_std_from_confidence']


@dataclass
class AlignmentConfig:
    """Parameters of :func:`align_photometric` (defaults tuned for 80..320 pixel wide processing images).

    num_levels: pyramid levels, each half the size of the previous one (level 0 = the images as given).
    finest_level: the finest level that is solved (0 = full size; 1 = stop at half size, 4x cheaper).
    min_level_size: levels whose shorter side is below this many pixels are skipped.
    max_iterations: LM iterations per level.
    step_tolerance: a level stops when the rotation step (rad) and the translation step relative to the median
        scene depth both fall below this.
    huber_k: Huber threshold in units of the robust residual scale (1.345 = 95 % Gaussian efficiency).
    outlier_k: residuals beyond this many robust scales get weight 0 (occlusions, specularities, moving things),
        on all but the coarsest level; 0 disables the cut (pure Huber).
    affine_brightness: estimate I_ref ~ a * I_src + b jointly with the pose (else a=1, b=0 fixed).
        The coarsest level keeps a = 1 and sets b to the median intensity difference: far from the optimum a
        free gain shrinks towards 0 (a flat warped image fits a misaligned reference better), which kills the
        pose gradient.
    brightness_prior: weight (per unit confidence, relative to the squared intensity residuals) of a weak prior
        pulling (a, b) towards (1, 0) on the finer levels (regularises textureless pairs).
    min_valid_fraction, min_valid_pixels: fewer valid (depth, in view) pixels than both -> not converged.
    max_residual_ratio: convergence also requires robust_scale(residual) / robust_scale(I_ref) below this
        (aligned images explain most of the reference's contrast; unrelated images do not).
    covariance_inflation: multiplies the i.i.d. covariance to account for correlated pixel noise.
    lm_lambda0: initial LM damping (relative to diag(H)).
    max_pixels: per level, at most about this many pixels are used - the strongest-gradient pixel of each cell
        of a grid (0 = every pixel with depth). The full-size warp is still computed; the residuals, Jacobians
        and normal equations scale with this number.
    """
    num_levels: int = 4
    finest_level: int = 0
    min_level_size: int = 12
    max_iterations: int = 12
    step_tolerance: float = 2e-4
    huber_k: float = 1.345
    outlier_k: float = 5.0
    affine_brightness: bool = True
    brightness_prior: float = 1e-3
    min_valid_fraction: float = 0.05
    min_valid_pixels: int = 50
    max_residual_ratio: float = 0.75
    covariance_inflation: float = 20.0
    lm_lambda0: float = 1e-3
    max_pixels: int = 3000


@dataclass
class AlignmentResult:
    """Outcome of one alignment.

    T_src_ref_44: refined pose (float64 numpy) mapping reference-camera points into the source camera.
    covariance_66: covariance of the left-perturbation twist (rho, omega) of T_src_ref (translation first,
        metres and radians), i.e. ``T_true = exp(xi) T_src_ref``, xi ~ N(0, covariance_66).
    converged: the solver reached a minimum with enough valid pixels and a plausible residual.
    reason: why not converged (None when converged).
    cost: final mean robust cost per valid pixel (intensity units^2).
    residual_ratio: robust residual scale / robust scale of the reference intensities (0 = perfect fit).
    num_valid: valid pixels at the finest level solved. iterations: LM iterations over all levels.
    brightness: (a, b) of I_ref ~ a I_src + b.
    depth_offset_sensitivity, depth_scale_sensitivity: (6,) change of the solution's twist (rho, omega) per unit
        error of the reference depth: an inverse-depth offset (1/m, rho -> rho + c) and a relative scale (depth ->
        (1 + s) depth). A scale error moves the translation along itself; an inverse-depth offset - what pose
        errors leave in a plane-swept depth - moves the rotation about the axis perpendicular to the baseline
        and the optical axis (rotation-translation ambiguity). Used to widen the factor's covariance.
    """
    T_src_ref_44: np.ndarray
    covariance_66: np.ndarray
    converged: bool
    reason: Optional[str]
    cost: float
    residual_ratio: float
    num_valid: int
    iterations: int
    brightness: Tuple[float, float] = (1.0, 0.0)
    level_log: List[dict] = field(default_factory=list)
    depth_offset_sensitivity: np.ndarray = field(default_factory=lambda: np.zeros(6))
    depth_scale_sensitivity: np.ndarray = field(default_factory=lambda: np.zeros(6))

    @property
    def T_ref_src_44(self) -> np.ndarray:
        return np.linalg.inv(self.T_src_ref_44)

    def between_covariance_gtsam(self, depth_scale_sigma: float = 0.0, translation_sigma_rel: float = 0.0,
                                 inv_depth_offset_sigma: float = 0.0) -> np.ndarray:
        """Covariance for ``gtsam.BetweenFactorPose3(ref, src, T_ref_src)``.

        gtsam's between error is ``Log(T_meas^-1 T_ref^-1 T_src)``: a right perturbation of ``T_ref_src`` with the
        tangent ordered (omega, rho). With ``T_src_ref = exp(xi) T``, ``T_ref_src = T^-1 exp(-xi)``, so the right
        perturbation of T_ref_src is ``-xi`` (same covariance), reordered rotation first.

        The per-pixel covariance cannot see errors of the reference depth that are common to all pixels; they are
        added as ``sigma^2 v v^T`` with ``v`` the solution's sensitivity to them (see the fields):
        ``depth_scale_sigma`` (relative scale of the depth: monocular scale ambiguity, it moves the translation
        along itself) and ``inv_depth_offset_sigma`` (1/m: a constant inverse-depth error, what rotation errors of
        the poses leave in a plane-swept depth; it moves the rotation). ``translation_sigma_rel`` adds an
        isotropic translation std relative to ``|t|`` for errors in the depth's structure.
        """
        cov = np.array(self.covariance_66, dtype=np.float64, copy=True)
        t = self.T_src_ref_44[:3, 3]
        if depth_scale_sigma > 0:
            v = np.asarray(self.depth_scale_sensitivity, dtype=np.float64)
            cov += depth_scale_sigma ** 2 * np.outer(v, v)
        if inv_depth_offset_sigma > 0:
            v = np.asarray(self.depth_offset_sensitivity, dtype=np.float64)
            cov += inv_depth_offset_sigma ** 2 * np.outer(v, v)
        if translation_sigma_rel > 0:
            cov[:3, :3] += (translation_sigma_rel ** 2 * float(t @ t)) * np.eye(3)
        return twist_to_gtsam_order(cov)


def twist_to_gtsam_order(cov_66: np.ndarray) -> np.ndarray:
    """Reorder a (rho, omega) covariance to gtsam's Pose3 tangent order (omega, rho)."""
    p = [3, 4, 5, 0, 1, 2]
    return np.asarray(cov_66)[np.ix_(p, p)]


def to_gray(image, dtype=torch.float32) -> torch.Tensor:
    """Grey image (H, W) in [0, 1] from uint8 HxWx3 RGB, HxW uint8, float HxW / HxWx3 in [0, 1] or a
    (1|3, H, W) tensor. Rec. 601 luma weights."""
    t = torch.as_tensor(np.ascontiguousarray(image)) if isinstance(image, np.ndarray) else image
    is_uint8 = t.dtype == torch.uint8
    t = t.to(dtype)
    if is_uint8:
        t = t / 255.0
    if t.dim() == 3:
        if t.shape[-1] == 3 and t.shape[0] != 3:      # HxWx3
            t = t.permute(2, 0, 1)
        if t.shape[0] == 3:
            w = torch.tensor([0.299, 0.587, 0.114], dtype=dtype, device=t.device)
            t = (t * w[:, None, None]).sum(0)
        else:
            t = t[0]
    return t


def resample_map(maps_chw: torch.Tensor, valid_hw: torch.Tensor, K_src_33, K_dst_33, size: Tuple[int, int]
                 ) -> Tuple[torch.Tensor, torch.Tensor]:
    """Resample maps defined on camera grid ``K_src`` (their own size) onto grid ``K_dst`` of ``size`` = (H, W),
    averaging only valid pixels.

    Both grids belong to the same pinhole camera (they differ in scale and offset only: an image and its
    pyramid level, or an image and its DPV's stride-4 grid), so destination pixel u reads the source at
    ``u_src = fx_src / fx_dst * (u - cx_dst) + cx_src`` (same for v): bilinear, pixel centres at integer
    coordinates. ``maps_chw``: (C, h, w); returns ((C, H, W) with 0 where invalid, (H, W) validity: at least half
    of the interpolation weight came from valid pixels).
    """
    C, hs, ws = maps_chw.shape
    H, W = int(size[0]), int(size[1])
    dt = maps_chw.dtype
    ax, ay, bx, by = affine = camera_grid_affine(K_src_33, K_dst_33)
    if (H, W) == (hs, ws) and abs(ax - 1) < 1e-9 and abs(ay - 1) < 1e-9 and abs(bx) < 1e-9 and abs(by) < 1e-9:
        return torch.where(valid_hw[None], maps_chw, torch.zeros_like(maps_chw)), valid_hw
    grid = camera_resample_grid(affine, (hs, ws), (H, W), dt).to(maps_chw.device)
    vf = valid_hw.to(dt)
    src = torch.cat([torch.where(valid_hw[None], maps_chw, torch.zeros_like(maps_chw)) * vf[None], vf[None]], 0)
    out = F.grid_sample(src[None], grid, mode='bilinear', padding_mode='zeros', align_corners=True)[0]
    den = out[-1]
    ok = den >= 0.5
    res = torch.where(ok[None], out[:-1] / den.clamp_min(1e-6)[None], torch.zeros_like(out[:-1]))
    return res, ok


def inverse_depth_std_from_confidence(conf_hw, depths_d) -> torch.Tensor:
    """Approximate std of the inverse depth (1/m) of a DPV estimate from its confidence (paper eq. 2).

    The confidence is the probability mass within +-1 plane of the estimate, i.e. over 3 planes. For a Gaussian
    DPV with a std of s planes that mass is ``erf(1.5 / (s sqrt 2))``, so ``s = 1.5 / (sqrt 2 erfinv(conf))``
    (about 1.2 / conf for small confidences), kept between half a plane (the resolution of the expectation)
    and the std of a uniform DPV (D / sqrt 12). Planes are uniform in inverse depth, so the std in inverse
    depth is s times the plane spacing.
    """
    d = torch.as_tensor(depths_d, dtype=torch.float64).reshape(-1)
    D = d.numel()
    spacing = float((1.0 / d[0] - 1.0 / d[-1]).abs()) / max(D - 1, 1)
    c = torch.as_tensor(conf_hw).to(torch.float32).clamp(1e-3, 1.0 - 1e-6)
    s = 1.5 / (math.sqrt(2.0) * torch.erfinv(c))
    return s.clamp(min=0.5, max=D / math.sqrt(12.0)) * spacing


def pose_error(T_a_44: np.ndarray, T_b_44: np.ndarray) -> Tuple[float, float]:
    """(translation error in metres, rotation error in degrees) of ``T_a^-1 T_b``."""
    return relative_pose_error_np(T_a_44, T_b_44)


# ----------------------------------------------------------------------------------------------------------------

_SOBEL_X = torch.tensor([[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]]) / 8.0


def _gradients(img_hw: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """Sobel derivatives d/du, d/dv (per pixel, replicate border)."""
    k = _SOBEL_X.to(img_hw.dtype).to(img_hw.device)
    x = F.pad(img_hw[None, None], (1, 1, 1, 1), mode='replicate')
    gx = F.conv2d(x, k[None, None])[0, 0]
    gy = F.conv2d(x, k.t()[None, None])[0, 0]
    return gx, gy


def _pyramid(img_hw: torch.Tensor, K_33: torch.Tensor, levels: int):
    """[(image, K)] from level 0 (given) to ``levels-1``, each 2x2 average-pooled."""
    out = [(img_hw, K_33)]
    for _ in range(1, levels):
        im, K = out[-1]
        if min(im.shape) < 4:
            break
        out.append((F.avg_pool2d(im[None, None], 2)[0, 0], scale_intrinsics(K, 0.5, 0.5)))
    return out


def _robust_scale(r: torch.Tensor) -> torch.Tensor:
    med = r.median()
    return 1.4826 * (r - med).abs().median()


def _huber_weight(r: torch.Tensor, delta: torch.Tensor, cut: Optional[torch.Tensor] = None) -> torch.Tensor:
    """IRLS weight of the Huber norm; 0 beyond ``cut`` (outlier rejection) when given."""
    a = r.abs()
    w = torch.where(a <= delta, torch.ones_like(a), delta / a.clamp_min(1e-12))
    return w if cut is None else torch.where(a <= cut, w, torch.zeros_like(w))


def _huber_cost(r: torch.Tensor, delta: torch.Tensor, cut: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Huber norm; constant beyond ``cut`` when given (truncated: an outlier costs the same wherever it is)."""
    a = r.abs() if cut is None else r.abs().clamp(max=cut)
    return torch.where(a <= delta, 0.5 * a * a, delta * (a - 0.5 * delta))


def _mean_cost(ev: '_Eval', sigma: torch.Tensor, delta: torch.Tensor, a: float, b: float, prior: float,
               cut: Optional[torch.Tensor] = None) -> float:
    """Weighted mean (truncated) Huber cost plus the brightness prior 0.5 * prior * ((a-1)^2 + b^2)."""
    w0 = ev.base_weight(sigma)
    data = float((w0 * _huber_cost(ev.r, delta, cut)).sum() / w0.sum().clamp_min(1e-12))
    return data + 0.5 * prior * ((a - 1.0) ** 2 + b ** 2)


def _select_pixels(ref_hw: torch.Tensor, usable_hw: torch.Tensor, max_pixels: int) -> torch.Tensor:
    """Flat indices of the pixels to align with: all usable ones, or (when there are more than ``max_pixels``)
    the one with the strongest reference gradient in each cell of a grid sized to give about ``max_pixels``
    cells - informative pixels spread over the whole image (as in DSO's point selection)."""
    H, W = ref_hw.shape
    n_usable = int(usable_hw.sum())
    if max_pixels <= 0 or n_usable <= max_pixels:
        return usable_hw.reshape(-1).nonzero().squeeze(1)
    gx, gy = _gradients(ref_hw)
    score = torch.where(usable_hw, gx * gx + gy * gy + 1e-12, torch.full_like(gx, -1.0))
    cell = max(1, int(math.ceil(math.sqrt(n_usable / max_pixels))))
    pad_h, pad_w = (-H) % cell, (-W) % cell
    padded = F.pad(score[None, None], (0, pad_w, 0, pad_h), value=-1.0)
    best, idx = F.max_pool2d(padded, cell, return_indices=True)
    best, idx = best.reshape(-1), idx.reshape(-1)
    keep = best > 0
    idx = idx[keep]
    # indices refer to the padded grid: convert to the image grid
    v, u = idx // (W + pad_w), idx % (W + pad_w)
    return (v * W + u).sort().values


class ImagePyramid:
    """Grey image pyramid of one frame, level 0 = the image as given, each next level 2x2 average-pooled with its
    intrinsics scaled. As a source it also carries the Sobel gradients of each level (built on first use). Build
    it once per frame and pass it to :class:`Aligner` / :func:`align_photometric` instead of the image when the
    frame is aligned more than once (a window's keyframes are)."""

    def __init__(self, image, K_33, num_levels: int, dtype=torch.float32):
        gray = to_gray(image, dtype)
        self.K = _as_tensor(K_33, torch.float64, gray.device)
        self.levels = _pyramid(gray, self.K, num_levels)
        self.num_levels = int(num_levels)
        self._stacks = {}

    @property
    def shape(self) -> Tuple[int, int]:
        return tuple(self.levels[0][0].shape)

    def source_stack(self, level: int) -> torch.Tensor:
        """(1, 3, h, w): intensity and its d/du, d/dv at ``level``."""
        if level not in self._stacks:
            im = self.levels[level][0]
            gx, gy = _gradients(im)
            self._stacks[level] = torch.stack([im, gx, gy])[None]
        return self._stacks[level]


class _RefLevel:
    """Everything of one reference pyramid level that does not depend on the pose or the source."""

    def __init__(self, ref_hw, depth_hw, conf_hw, K_33, rho_std_hw=None, max_pixels: int = 0):
        self.h, self.w = ref_hw.shape
        self.K = K_33
        has = depth_hw > 0
        usable = has & (conf_hw > 0)
        self.usable_fraction = float(usable.float().mean())
        idx = _select_pixels(ref_hw, usable, max_pixels)
        self.idx = idx
        self.X_ref = backproject(depth_hw[None], K_33[None])[0].reshape(3, -1).index_select(1, idx)   # 3,N
        self.I_ref = ref_hw.reshape(-1).index_select(0, idx)
        self.conf = conf_hw.reshape(-1).index_select(0, idx)
        self.d = depth_hw.reshape(-1).index_select(0, idx)
        self.rho_std = None if rho_std_hw is None else rho_std_hw.reshape(-1).index_select(0, idx)
        self.median_depth = float(depth_hw[has].median()) if bool(has.any()) else 1.0


def _sample_source(src_1chw: torch.Tensor, X_ref_3n: torch.Tensor, K_33: torch.Tensor, T_src_ref_44: torch.Tensor):
    """The source channels at the projections of reference points ``X_ref`` (3, N): the warp of
    :func:`dpv_sensor.core.geometry.warp_image_with_depth` evaluated at the selected pixels only (same transform,
    projection, bilinear ``grid_sample`` with ``align_corners=True`` and validity rule: in front of the camera and
    inside the image), so the cost scales with the number of selected pixels rather than the image size.

    Returns (C, N) samples, (N,) bool validity, and the (3, N) points in the source frame.
    """
    _, C, Hs, Ws = src_1chw.shape
    X = transform_points(T_src_ref_44[None], X_ref_3n[None])                    # 1,3,N
    uv, z = project(X, K_33[None])
    u, v = uv[0, 0], uv[0, 1]
    front = z[0] > Z_EPS
    valid = (front & (u >= -BOUNDS_TOL) & (u <= Ws - 1 + BOUNDS_TOL)
             & (v >= -BOUNDS_TOL) & (v <= Hs - 1 + BOUNDS_TOL))
    far = torch.full_like(u, -2.0)
    gx = torch.where(front, 2.0 * u / max(Ws - 1, 1) - 1.0, far)
    gy = torch.where(front, 2.0 * v / max(Hs - 1, 1) - 1.0, far)
    grid = torch.stack([gx, gy], -1).reshape(1, 1, -1, 2)
    out = F.grid_sample(src_1chw, grid, mode='bilinear', padding_mode='zeros', align_corners=True)
    return out.reshape(C, -1), valid, X[0]


class _Eval:
    """Residuals and Jacobians at one pose (and brightness) on one level."""

    def __init__(self, lv: _RefLevel, src_stack: torch.Tensor, T_44: torch.Tensor, a: float, b: float):
        dt = src_stack.dtype
        T = T_44.to(dt)
        ws, valid, X = _sample_source(src_stack, lv.X_ref, lv.K, T)
        m = valid.nonzero().squeeze(1)                                           # positions among the selection
        ws = ws.index_select(1, m)
        self.mask = m
        self.n = int(m.numel())
        self.Iw = ws[0]
        self.r = lv.I_ref.index_select(0, m) - (a * ws[0] + b)
        self.conf = lv.conf.index_select(0, m)
        self._ws = ws
        self._X = X.index_select(1, m)                                           # 3,N in the source frame
        self._a = a
        self._K = lv.K
        x, y, z = self._X
        K = lv.K
        fx, s, fy = K[0, 0], K[0, 1], K[1, 1]
        iz = 1.0 / z
        gx, gy = ws[1] * a, ws[2] * a
        # d(u,v)/dX, chained with the image gradient: g = [gx, gy] . dpi/dX   (N,3)
        du = torch.stack([fx * iz, s * iz, -(fx * x + s * y) * iz * iz], -1)
        dv = torch.stack([torch.zeros_like(z), fy * iz, -fy * y * iz * iz], -1)
        self._g = gx[:, None] * du + gy[:, None] * dv
        # Residual std caused by the reference depth's uncertainty: r depends on the inverse depth rho through
        # d(u, v)/d(rho) = depth * dpi/dX(X_src) t, so sigma_r = |g . t| * depth * sigma_rho.
        self._sigma_depth = None
        if lv.rho_std is not None:
            t = T_44[:3, 3].to(dt)
            self._sigma_depth = (self._g @ t).abs() * lv.d.index_select(0, m) * lv.rho_std.index_select(0, m)

    def base_weight(self, sigma: torch.Tensor) -> torch.Tensor:
        """Per-pixel weight before the robust norm: confidence times sigma^2 / (sigma^2 + sigma_depth^2)."""
        if self._sigma_depth is None:
            return self.conf
        s2 = sigma * sigma
        return self.conf * s2 / (s2 + self._sigma_depth ** 2)

    def jacobian(self, affine: bool) -> torch.Tensor:
        """d r / d (rho, omega[, a, b]) for the left perturbation exp(xi) T_src_ref, shape (N, 6|8)."""
        g = self._g
        # dX/dxi = [I | -[X]x]  ->  g . [I | -[X]x] = [g, X x g]
        X = self._X.t()
        J_pose = -torch.cat([g, torch.cross(X, g, dim=-1)], -1)
        if not affine:
            return J_pose
        return torch.cat([J_pose, -self.Iw[:, None], -torch.ones_like(self.Iw)[:, None]], -1)


def _exp_left(xi_6: np.ndarray, T_44: torch.Tensor) -> torch.Tensor:
    """``exp(xi) T`` for a twist (rho, omega): the SE(3) exponential of ``geometry.se3_exp``, evaluated by
    gtsam's ``Pose3.Expmap`` (same map, tangent ordered (omega, rho)) because it is ~100x cheaper than a batched
    torch call for a single twist."""
    E = gtsam.Pose3.Expmap(np.concatenate([xi_6[3:], xi_6[:3]])).matrix()
    return torch.from_numpy(E) @ T_44


def _as_tensor(x, dtype, device=None) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x.to(dtype=dtype, device=device)
    return torch.as_tensor(np.asarray(x), dtype=dtype, device=device)


class Aligner:
    """Photometric alignment against one reference view (paper eq. 11, coarse to fine); see the module doc.

    The reference's pyramid, depth / confidence resampled to every level and the pixel selection are prepared
    once; :meth:`align` then aligns any number of source images (or :class:`ImagePyramid` s) against it.

    Args:
        ref_image: the reference image (uint8 RGB HxWx3, grey HxW, float in [0, 1] or tensors; see
            :func:`to_gray`) or its :class:`ImagePyramid`.
        depth_ref: reference z-depth (h, w) in metres, 0 / NaN = unknown. Any size: it is resampled onto the
            image pyramid through its intrinsics ``K_depth_33`` (the same camera scaled / shifted, e.g. the
            filter's quarter-resolution volume; default: ``K_33`` scaled by the size ratio, resize convention).
        K_33: intrinsics of the images (reference and sources share the camera).
        conf_ref: per-pixel weight (h, w) in [0, 1] on the depth grid (paper: the DPV confidence); default 1.
        inv_depth_std_ref: optional (h, w) standard deviation of the reference's inverse depth (1/m) on the depth
            grid (see :func:`inverse_depth_std_from_confidence`). Each pixel's weight is then also scaled by
            ``sigma^2 / (sigma^2 + sigma_depth^2)``, ``sigma_depth`` the intensity error its depth uncertainty
            causes at the current pose, so uncertain depth weakens the alignment (and widens its covariance).
        config: :class:`AlignmentConfig`.
    """

    def __init__(self, ref_image, depth_ref, K_33, conf_ref=None, K_depth_33=None, inv_depth_std_ref=None,
                 config: Optional[AlignmentConfig] = None):
        cfg = self.config = config or AlignmentConfig()
        dtype = self.dtype = torch.float32
        pyr = ref_image if isinstance(ref_image, ImagePyramid) else ImagePyramid(ref_image, K_33, cfg.num_levels)
        if pyr.num_levels < cfg.num_levels:
            raise ValueError(f'the reference pyramid has {pyr.num_levels} levels, the config asks for {cfg.num_levels}')
        self.pyramid = pyr
        device = pyr.levels[0][0].device
        K = pyr.K
        depth = _as_tensor(depth_ref, dtype, device)
        conf = torch.ones_like(depth) if conf_ref is None else _as_tensor(conf_ref, dtype, device)
        valid_d = torch.isfinite(depth) & (depth > 0) & torch.isfinite(conf)
        conf = torch.where(valid_d, conf.clamp(0.0, 1.0), torch.zeros_like(conf))
        rho_std = None
        if inv_depth_std_ref is not None:
            rho_std = _as_tensor(inv_depth_std_ref, dtype, device)
            rho_std = torch.where(valid_d & torch.isfinite(rho_std), rho_std.clamp_min(0.0),
                                  torch.zeros_like(rho_std))
        H, W = pyr.shape
        if K_depth_33 is None:
            K_depth = scale_intrinsics(K, depth.shape[1] / W, depth.shape[0] / H)   # resize convention
        else:
            K_depth = _as_tensor(K_depth_33, torch.float64, device)
        maps = torch.stack([depth, conf] + ([] if rho_std is None else [rho_std]))
        levels = [lvl for lvl in range(min(len(pyr.levels), cfg.num_levels) - 1, cfg.finest_level - 1, -1)
                  if min(pyr.levels[lvl][0].shape) >= cfg.min_level_size]
        if not levels:
            levels = [min(cfg.finest_level, len(pyr.levels) - 1)]
        self.levels = levels
        self.ref_levels = {}
        for li in levels:
            im_r, K_l = pyr.levels[li]
            m_l, ok_d = resample_map(maps, valid_d, K_depth, K_l, tuple(im_r.shape))
            d_l = torch.where(ok_d, m_l[0], torch.zeros_like(m_l[0]))
            self.ref_levels[li] = _RefLevel(im_r, d_l, m_l[1], K_l.to(dtype),
                                            None if rho_std is None else m_l[2], cfg.max_pixels)

    def align(self, src_image, T_src_ref_init=None) -> AlignmentResult:
        """Align a source image (same size and camera as the reference, or its :class:`ImagePyramid`) starting
        from ``T_src_ref_init`` (4x4 mapping reference points into the source camera; default identity)."""
        cfg = self.config
        src = src_image if isinstance(src_image, ImagePyramid) else ImagePyramid(src_image, self.pyramid.K,
                                                                                    cfg.num_levels, self.dtype)
        if src.shape != self.pyramid.shape:
            raise ValueError(f'reference {self.pyramid.shape} and source {src.shape} images differ in size')
        T = torch.eye(4, dtype=torch.float64) if T_src_ref_init is None else _as_tensor(T_src_ref_init,
                                                                                       torch.float64)
        a, b = 1.0, 0.0
        n_par = 8 if cfg.affine_brightness else 6
        total_iters = 0
        log: List[dict] = []
        final = None
        for level_no, li in enumerate(self.levels):
            # The coarsest level keeps the gain fixed (a = 1, offset b = median intensity difference): far from
            # the optimum a free gain collapses towards 0. The finer levels estimate (a, b) with the pose.
            affine = cfg.affine_brightness and level_no > 0
            prior = float(cfg.brightness_prior) if affine else 0.0
            lv = self.ref_levels[li]
            stack = src.source_stack(li)
            if lv.X_ref.shape[1] < 8 + n_par:
                log.append({'level': li, 'n': 0})
                continue
            state = _Eval(lv, stack, T, a, b)
            if state.n < n_par + 8:
                log.append({'level': li, 'n': state.n})
                final = (lv, state, None)
                continue
            if cfg.affine_brightness and level_no == 0:
                b = float((state.r + b).median())
                state = _Eval(lv, stack, T, a, b)
            sigma = _robust_scale(state.r).clamp_min(1e-3)
            lam = cfg.lm_lambda0
            iters = 0
            stalled = False
            small_step = False
            last_step = float('inf')
            for iters in range(1, cfg.max_iterations + 1):   # noqa: B007 (the count is read after the loop)
                delta = cfg.huber_k * sigma
                # Outlier rejection from the second level on (at the coarsest, misaligned pixels look like
                # outliers).
                cut = cfg.outlier_k * sigma if (level_no > 0 and cfg.outlier_k > 0) else None
                w = state.base_weight(sigma) * _huber_weight(state.r, delta, cut)
                J = state.jacobian(affine)
                Jw = J * w[:, None]
                Hm = (Jw.t() @ J).to(torch.float64)
                g = (Jw.t() @ state.r).to(torch.float64)
                if affine and prior > 0:
                    c_sum = float(state.base_weight(sigma).sum())
                    Hm[6, 6] += prior * c_sum
                    Hm[7, 7] += prior * c_sum
                    g[6] += prior * c_sum * (a - 1.0)
                    g[7] += prior * c_sum * b
                cost0 = _mean_cost(state, sigma, delta, a, b, prior, cut)
                accepted = False
                for _ in range(6):
                    A = Hm + lam * torch.diag(torch.diagonal(Hm).clamp_min(1e-9))
                    try:
                        step = -torch.linalg.solve(A, g)
                    except RuntimeError:
                        lam *= 10.0
                        continue
                    if not bool(torch.isfinite(step).all()):
                        lam *= 10.0
                        continue
                    T_new = _exp_left(step[:6].numpy(), T)
                    a_new = a + float(step[6]) if affine else a
                    b_new = b + float(step[7]) if affine else b
                    cand = _Eval(lv, stack, T_new, a_new, b_new)
                    if cand.n >= n_par + 8:
                        cost1 = _mean_cost(cand, sigma, delta, a_new, b_new, prior, cut)
                        if cost1 <= cost0:
                            T, a, b, state = T_new, a_new, b_new, cand
                            lam = max(lam / 10.0, 1e-7)
                            accepted = True
                            break
                    lam *= 10.0
                if not accepted:
                    stalled = True
                    break
                sigma = _robust_scale(state.r).clamp_min(1e-3)
                rot = float(step[3:6].norm())
                trans = float(step[:3].norm()) / max(lv.median_depth, 1e-6)
                last_step = max(rot, trans)
                if last_step < cfg.step_tolerance:
                    small_step = True
                    break
            # Out of iterations but only creeping (steps within 10x the tolerance): also a minimum.
            creeping = last_step < 10.0 * cfg.step_tolerance
            total_iters += iters
            log.append({'level': li, 'n': state.n, 'iterations': iters, 'sigma': float(sigma),
                        'stalled': stalled, 'small_step': small_step})
            final = (lv, state, (stalled or small_step or creeping))
        return _finish(final, T, a, b, cfg, total_iters, log, n_par)


def align_photometric(ref_image, src_image, depth_ref, K_33, T_src_ref_init=None, conf_ref=None,
                      K_depth_33=None, config: Optional[AlignmentConfig] = None,
                      inv_depth_std_ref=None) -> AlignmentResult:
    """Align ``src_image`` to ``ref_image`` given the reference depth (paper eq. 11, coarse to fine).

    One-shot form of ``Aligner(ref_image, depth_ref, K_33, conf_ref, K_depth_33, inv_depth_std_ref,
    config).align(src_image, T_src_ref_init)``; see :class:`Aligner` for the arguments (images may also be
    :class:`ImagePyramid` s). ``T_src_ref_init``: initial 4x4 pose mapping reference points into the source
    camera (default identity). Returns an :class:`AlignmentResult` (pose, covariance, convergence flag and
    reason, cost, valid pixels).
    """
    return Aligner(ref_image, depth_ref, K_33, conf_ref=conf_ref, K_depth_33=K_depth_33,
                   inv_depth_std_ref=inv_depth_std_ref, config=config).align(src_image, T_src_ref_init)


def _finish(final, T, a, b, cfg: AlignmentConfig, total_iters, log, n_par) -> AlignmentResult:
    T_np = T.detach().cpu().numpy().astype(np.float64)
    big = np.eye(6) * 1e6
    if final is None:
        return AlignmentResult(T_np, big, False, 'too few pixels with depth', float('inf'), float('inf'), 0,
                               total_iters, (a, b), log)
    lv, state, reached_min = final
    n = state.n
    # fraction of the image with depth that lands inside the source (estimated on the selected pixels)
    frac = lv.usable_fraction * n / max(int(lv.idx.numel()), 1)
    if n < max(cfg.min_valid_pixels, n_par + 8) or frac < cfg.min_valid_fraction:
        return AlignmentResult(T_np, big, False, f'too few valid pixels ({n}, {100 * frac:.1f} % of the image; '
                               f'need {cfg.min_valid_pixels} and {100 * cfg.min_valid_fraction:.0f} %)',
                               float('inf'), float('inf'), n, total_iters, (a, b), log)
    sigma = _robust_scale(state.r).clamp_min(1e-4)
    delta = cfg.huber_k * sigma
    cut = cfg.outlier_k * sigma if cfg.outlier_k > 0 else None
    hub = _huber_weight(state.r, delta, cut)
    n_in = int((hub > 0).sum())
    w = (state.base_weight(sigma) * hub).to(torch.float64)
    J = state.jacobian(cfg.affine_brightness).to(torch.float64)
    Hm = (J * w[:, None]).t() @ J
    r64 = state.r.to(torch.float64)
    # Residual variance from the relative weights (confidence x Huber); the depth-uncertainty factor
    # sigma^2 / (sigma^2 + sigma_depth^2) is an absolute variance ratio and stays out of this estimate, so
    # uncertain depth widens the covariance instead of cancelling out.
    w_rel = (state.conf * hub).to(torch.float64)
    s2 = float((w_rel * r64 * r64).sum() / max(n_in - n_par, 1))
    # Sensitivity of the solution to a global error of the reference depth ("consider" parameters, not
    # estimated): an inverse-depth offset c (rho -> rho + c) and a scale s (depth -> (1 + s) depth). With
    # dr/drho = -(g . t) depth (g = a grad I . dpi/dX, t = translation of T_src_ref):
    #   dr/dc = -(g . t) depth,  dr/ds = (g . t).   The GN solution moves by dx = -H^-1 J^T W (dr/dp) dp.
    t_vec = T[:3, 3].to(state._g.dtype)
    gt = (state._g @ t_vec).to(torch.float64)
    d_sel = lv.d.index_select(0, state.mask).to(torch.float64)
    J_c = -gt * d_sel
    J_s = gt
    sens_c = np.zeros(6)
    sens_s = np.zeros(6)
    try:
        H_inv = torch.linalg.inv(Hm)
        cov = (H_inv * s2)[:6, :6].numpy()
        Jw = J * w[:, None]
        sens_c = -(H_inv @ (Jw.t() @ J_c))[:6].numpy()
        sens_s = -(H_inv @ (Jw.t() @ J_s))[:6].numpy()
    except RuntimeError:
        cov = big
    cov = 0.5 * (cov + cov.T) * cfg.covariance_inflation
    ok_cov = bool(np.all(np.isfinite(cov))) and bool(np.all(np.linalg.eigvalsh(cov) > 0))
    if not ok_cov:
        cov = big
    cost = _mean_cost(state, sigma, delta, a, b, 0.0, cut)
    ref_scale = float(_robust_scale(lv.I_ref.index_select(0, state.mask)).clamp_min(1e-4))
    ratio = float(sigma) / ref_scale
    reason = None
    if not (np.all(np.isfinite(T_np)) and math.isfinite(cost)):
        reason = 'diverged (non-finite pose or cost)'
    elif not reached_min:
        reason = f'no convergence within {cfg.max_iterations} iterations'
    elif ratio > cfg.max_residual_ratio:
        reason = f'residual too high (ratio {ratio:.2f} > {cfg.max_residual_ratio:.2f})'
    elif not ok_cov:
        reason = 'degenerate Hessian'
    return AlignmentResult(T_np, cov, reason is None, reason, cost, ratio, n, total_iters, (a, b), log,
                           depth_offset_sensitivity=sens_c, depth_scale_sensitivity=sens_s)
