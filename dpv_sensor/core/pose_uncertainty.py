"""Pose uncertainty in the depth measurement: how far a source's pose error moves a pixel's match, in depth planes,
and the measurement widened by it.

A plane sweep measures depth through the image position of a reference pixel's match in each source view. An error
in the source's pose relative to the reference moves that position by some pixels; along the epipolar line this is
indistinguishable from a change of depth. This module turns the relative pose uncertainty of every source into a
per-pixel standard deviation of the measured inverse depth, and widens the measurement's distribution over the
depth planes by it (a Gaussian in plane index, the planes being uniform in inverse depth), so that the filter and
the published confidence carry the pose error as well as the matching ambiguity. The maths, with the reasons for the
default drift figures, is in docs/pose_uncertainty.md.

1. **Relative pose uncertainty** (:func:`relative_pose_sigma`), per source, as isotropic per-axis standard deviations
   ``(sigma_rot_rad, sigma_trans_m)`` of the source's pose relative to the reference, the sum of independent terms:

   * drift of the odometry along the path between the two views (length ``L`` metres, rotation ``A`` degrees):
     error magnitudes ``trans_per_m * L`` and ``rot_deg_per_m * L + rot_per_deg * A`` (an error vector of magnitude
     ``m`` in a random direction has per-axis std ``m / sqrt(3)``);
   * what the odometry says about itself (:func:`odometry_sigma`), used instead of the drift terms, from the first
     of these that applies:

     - the growth of the pose covariance between the two views, when it grows (the mean rotation variance is
       larger at the later view): for integrated odometry the covariance of the relative motion. Its translation
       growth also holds the heading error accumulated before the first view, levered by the step (with its
       cross-covariance to the position), which does not enter the relative motion: on a long path it overstates
       the relative translation by up to ten times, and where the path returns towards where a heading error began
       the position variance even shrinks (so it is no test of growth). So the translation variance taken from it
       is capped at what ``cov_trans_per_m`` of the path (the relative motion's own translation error) plus the
       rotation growth's lever within the segment give, ``(cov_trans_per_m L)^2 / 3 + var_rot L^2 / 3``, and is
       that bound where the position variance did not grow;
     - else the twist covariance integrated over the interval (a pose covariance that stays constant, as
       diff_drive_controller's ``pose_covariance_diagonal``, says nothing about the relative motion; the motion
       noise is then in ``twist.covariance``): the mean of the two views' twist covariances, read as a rate in the
       child frame, integrated over the time between them along their relative motion
       (:func:`dpv_sensor.core.odometry_covariance.twist_step_covariance`), per axis the trace of each block / 3;
   * a camera-odometry time offset of std ``sync_s``: with body velocities ``v``, ``w`` the pose at ``t + tau`` is
     off by ``tau * (v, w)``, and the relative pose of two views by ``tau`` times the *difference* of their
     velocities (a constant offset cancels for constant motion).

2. **Pixel shift** (:func:`match_shift_px`): a rotation error of per-axis std ``s_r`` moves a pixel at distance ``r``
   from the principal point by ``f s_r`` (about the x and y axes) and ``r s_r`` (about z); a translation error
   ``s_t`` at depth ``d`` by ``f s_t / d`` and ``r s_t / d``. The component along the epipolar line (one of two image
   directions) has std ``sqrt(f^2 + r^2 / 2) * sqrt(s_r^2 + (s_t / d)^2)`` pixels.

3. **Inverse-depth std per source**: the band ``[d / k, d k]`` (k = 1.25) spans ``span`` pixels of the epipolar line
   (``parallax.disparity_span``) and ``rho (k - 1 / k)`` in inverse depth ``rho = 1 / d``, so
   ``sigma_rho = shift_px * rho (k - 1 / k) / span``. The sources' errors are combined as independent measurements
   of one inverse depth, ``1 / sigma^2 = sum_n 1 / sigma_n^2``; a source that does not see the pixel adds nothing.

4. **Widening** (:func:`widen_planes`): the measurement's probabilities over the D planes are convolved, per pixel,
   with a Gaussian of ``sigma_rho / delta_rho`` planes (``delta_rho`` = the plane spacing in inverse depth): a
   mixture of the two nearest of a fixed ladder of widths, so the cost is a few (D x D) matrix products.

torch and numpy only; no ROS.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import numpy as np
import torch

from dpv_sensor.core import dpv as dpv_ops
from dpv_sensor.core.pose_math import rotation_angle_np
from dpv_sensor.core.odometry_covariance import OdometryCovariance, twist_step_covariance
from dpv_sensor.core.parallax import BAND_RATIO

__all__ = ['DriftModel', 'PoseSigma', 'relative_pose_sigma', 'path_between', 'covariance_sigma', 'twist_sigma',
           'odometry_sigma', 'GROWTH', 'TWIST', 'DRIFT', 'twist_between',
           'match_shift_px', 'inverse_depth_sigma', 'window_sigma_planes', 'confidence_factor', 'widen_planes',
           'WIDTH_LADDER', 'SQRT3', 'BAND_RATIO']

SQRT3 = math.sqrt(3.0)
# where the relative uncertainty of two odometry poses comes from (odometry_sigma)
GROWTH, TWIST, DRIFT = 'pose covariance growth', 'twist covariance', 'drift figures'
# Gaussian widths (planes) the per-pixel widening interpolates between; 0 = unchanged.
WIDTH_LADDER = (0.0, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0)


@dataclass(frozen=True)
class DriftModel:
    """How uncertain odometry is between two views (the ``odom_drift_*`` and ``odom_time_sync_ms`` settings).

    trans_per_m: translation error per metre travelled (0.02 = 2 % of the path). rot_deg_per_m: rotation error (deg)
    per metre travelled. rot_per_deg: rotation error per degree turned (0.02 = 2 %). sync_s: std of the camera-odometry
    time offset (s). cov_trans_per_m: the relative motion's own translation error per metre that caps a published
    covariance's translation growth (module doc, item 1; also with the drift terms off). All error figures are
    magnitudes of an error vector in a random direction.
    """
    trans_per_m: float = 0.02
    rot_deg_per_m: float = 1.0
    rot_per_deg: float = 0.02
    sync_s: float = 0.005
    cov_trans_per_m: float = 0.02


@dataclass(frozen=True)
class PoseSigma:
    """Per-axis standard deviations of a relative pose: rotation (rad) and translation (m)."""
    rot_rad: float
    trans_m: float


def path_between(poses_44: Sequence[np.ndarray]) -> Tuple[float, float]:
    """(metres, degrees) travelled along a chain of camera poses (``T_world_cam``, in time order): the sums of the
    consecutive steps' translations and rotation angles."""
    L = A = 0.0
    for a, b in zip(poses_44[:-1], poses_44[1:]):
        rel = np.linalg.inv(a) @ b
        L += float(np.linalg.norm(rel[:3, 3]))
        A += math.degrees(rotation_angle_np(rel[:3, :3]))
    return L, A


def _filled(diag_6: np.ndarray) -> bool:
    """A covariance's diagonal says something: finite, none negative, some positive."""
    return bool(np.all(np.isfinite(diag_6)) and np.all(diag_6 >= 0) and np.any(diag_6 > 0))


def covariance_sigma(cov_a_66: Optional[np.ndarray], cov_b_66: Optional[np.ndarray]) -> Optional[PoseSigma]:
    """Per-axis std of the motion between two odometry poses from their pose covariances (ROS order: x, y, z, then
    rotation about x, y, z; ``a`` the earlier, ``b`` the later): the growth of the mean diagonal variance from a to b
    (integrated odometry: the covariance of the relative motion). None when either is missing or not filled (a
    non-finite or negative diagonal, or none of it positive), or when the covariance does not grow: the mean rotation
    variance is not larger at b (a constant covariance, or one that shrank after a correction). Integrated odometry's
    rotation error only accumulates, while its position variance can shrink (the path returns towards where a heading
    error began, and the error that heading levered shrinks with it), so the translation is no test: where it does
    not grow, ``trans_m`` is NaN (the caller bounds it by the motion, :func:`odometry_sigma`)."""
    if cov_a_66 is None or cov_b_66 is None:
        return None
    da = np.diag(np.asarray(cov_a_66, np.float64).reshape(6, 6))
    db = np.diag(np.asarray(cov_b_66, np.float64).reshape(6, 6))
    if not (_filled(da) and _filled(db)):
        return None
    dt = float(db[:3].mean() - da[:3].mean())
    dr = float(db[3:].mean() - da[3:].mean())
    if not dr > 0:
        return None
    return PoseSigma(rot_rad=math.sqrt(dr), trans_m=math.sqrt(dt) if dt > 0 else math.nan)


def twist_sigma(twist_a_66: Optional[np.ndarray], twist_b_66: Optional[np.ndarray], T_a_44: np.ndarray,
                T_b_44: np.ndarray, dt_s: Optional[float]) -> Optional[PoseSigma]:
    """Per-axis std of the motion from pose a to pose b (``T_world_*``) from the twist covariances at the two poses
    (ROS order, child frame, per second) over the ``dt_s`` seconds between them: their mean integrated along the
    motion (:func:`dpv_sensor.core.odometry_covariance.twist_step_covariance`), the trace of each block / 3. None
    when either is missing or not filled (as for :func:`covariance_sigma`), or without a positive, finite ``dt_s``."""
    if twist_a_66 is None or twist_b_66 is None or dt_s is None or not (dt_s > 0 and math.isfinite(dt_s)):
        return None
    Qa = np.asarray(twist_a_66, np.float64).reshape(6, 6)
    Qb = np.asarray(twist_b_66, np.float64).reshape(6, 6)
    if not (np.all(np.isfinite(Qa)) and np.all(np.isfinite(Qb)) and _filled(np.diag(Qa)) and _filled(np.diag(Qb))):
        return None
    T_ab = np.linalg.inv(np.asarray(T_a_44, np.float64)) @ np.asarray(T_b_44, np.float64)
    S = twist_step_covariance(0.5 * (Qa + Qb), T_ab, float(dt_s))
    return PoseSigma(rot_rad=math.sqrt(max(float(np.trace(S[3:, 3:])) / 3.0, 0.0)),
                     trans_m=math.sqrt(max(float(np.trace(S[:3, :3])) / 3.0, 0.0)))


def odometry_sigma(chain_44: Sequence[np.ndarray], first, last, cov_trans_per_m: float
                   ) -> Tuple[Optional[PoseSigma], str]:
    """What the odometry says about the motion along ``chain_44`` (time order) from its covariances at the chain's
    first and last pose (:class:`~dpv_sensor.core.odometry_covariance.OdometryCovariance`, a bare 6x6 pose
    covariance, or None): (sigma, ``GROWTH``) from the pose covariance's growth, its translation capped (module
    docstring, item 1); else (sigma, ``TWIST``) from the twist covariance over the time between them; else (None,
    ``DRIFT``). Two stamps in the wrong order are swapped first (the growth is read from the earlier to the later).
    The translation from the growth is at most what the motion can hold (module docstring, item 1), and that bound
    where the position variance did not grow."""
    a, b = OdometryCovariance.of(first), OdometryCovariance.of(last)
    if a is None or b is None:
        return None, DRIFT
    chain = list(chain_44)
    if a.stamp is not None and b.stamp is not None and a.stamp > b.stamp:
        a, b, chain = b, a, chain[::-1]
    cov = covariance_sigma(a.pose_66, b.pose_66)
    if cov is not None:
        L, _ = path_between(chain)
        var_r = cov.rot_rad ** 2
        bound = (cov_trans_per_m * L) ** 2 / 3.0 + var_r * L ** 2 / 3.0
        var_t = min(cov.trans_m ** 2, bound) if math.isfinite(cov.trans_m) else bound
        return PoseSigma(rot_rad=cov.rot_rad, trans_m=math.sqrt(var_t)), GROWTH
    dt = None if a.stamp is None or b.stamp is None else float(b.stamp) - float(a.stamp)
    tw = twist_sigma(a.twist_66, b.twist_66, chain[0], chain[-1], dt)
    if tw is not None:
        return tw, TWIST
    return None, DRIFT


def twist_between(T_prev_44: np.ndarray, T_44: np.ndarray, dt: float) -> Optional[np.ndarray]:
    """World-frame velocity (vx, vy, vz, wx, wy, wz) of a camera moving from ``T_prev_44`` to ``T_44`` in ``dt``
    seconds (None when dt is not positive)."""
    if not (dt > 0 and math.isfinite(dt)):
        return None
    from scipy.spatial.transform import Rotation
    R = np.asarray(T_44, np.float64)[:3, :3] @ np.asarray(T_prev_44, np.float64)[:3, :3].T
    w = Rotation.from_matrix(R).as_rotvec() / dt
    v = (np.asarray(T_44, np.float64)[:3, 3] - np.asarray(T_prev_44, np.float64)[:3, 3]) / dt
    return np.concatenate([v, w])


def relative_pose_sigma(model: DriftModel, chain_44: Sequence[np.ndarray], *, odom_first=None, odom_last=None,
                        twist_ref_6: Optional[np.ndarray] = None, twist_src_6: Optional[np.ndarray] = None
                        ) -> PoseSigma:
    """Per-axis std of a source's pose relative to the reference (see the module docstring, item 1).

    chain_44: the poses from one of the two to the other in time order, the keyframes between them included (the
    path the drift accumulates over). odom_first / odom_last: what the odometry says about itself at the chain's
    first and last pose (:class:`~dpv_sensor.core.odometry_covariance.OdometryCovariance` or a bare pose
    covariance; used instead of the drift terms where :func:`odometry_sigma` gives a figure). twist_*_6: world-frame
    velocities of the two views (the time-offset term)."""
    L, A = path_between(list(chain_44))
    sig, _source = odometry_sigma(chain_44, odom_first, odom_last, model.cov_trans_per_m)
    if sig is not None:
        var_r, var_t = sig.rot_rad ** 2, sig.trans_m ** 2
    else:
        rot = math.radians(model.rot_deg_per_m * L + model.rot_per_deg * A) / SQRT3
        tr = model.trans_per_m * L / SQRT3
        var_r, var_t = rot ** 2, tr ** 2
    if model.sync_s > 0 and twist_ref_6 is not None and twist_src_6 is not None:
        d = np.asarray(twist_src_6, np.float64) - np.asarray(twist_ref_6, np.float64)
        var_t += (model.sync_s * float(np.linalg.norm(d[:3])) / SQRT3) ** 2
        var_r += (model.sync_s * float(np.linalg.norm(d[3:])) / SQRT3) ** 2
    return PoseSigma(rot_rad=math.sqrt(var_r), trans_m=math.sqrt(var_t))


def match_shift_px(depth_bhw: torch.Tensor, K_b33: torch.Tensor, sigma: PoseSigma) -> torch.Tensor:
    """(B, H, W) std (pixels of the grid K describes) of a match's position along the epipolar line caused by a
    relative pose error of per-axis std ``sigma``, for the points at ``depth_bhw`` (module docstring, item 2)."""
    B, H, W = depth_bhw.shape
    K = K_b33.to(torch.float32)
    f = 0.5 * (K[:, 0, 0] + K[:, 1, 1])
    u = torch.arange(W, dtype=torch.float32, device=depth_bhw.device)[None, None, :] - K[:, 0, 2][:, None, None]
    v = torch.arange(H, dtype=torch.float32, device=depth_bhw.device)[None, :, None] - K[:, 1, 2][:, None, None]
    r2 = u * u + v * v                                                      # B, H, W
    lever = torch.sqrt(f[:, None, None] ** 2 + 0.5 * r2)
    d = depth_bhw.to(torch.float32).clamp_min(1e-3)
    return lever * torch.sqrt(sigma.rot_rad ** 2 + (sigma.trans_m / d) ** 2)


def inverse_depth_sigma(depth_bhw: torch.Tensor, span_nbhw: torch.Tensor, shift_nbhw: torch.Tensor,
                        ratio: float) -> torch.Tensor:
    """(B, H, W) std of the measured inverse depth (1/m) from N sources (module docstring, item 3): per source
    ``shift * rho (ratio - 1 / ratio) / span`` (span and shift in the same pixels), combined as independent
    measurements; a source with no span (the point outside its view) adds nothing; inf where no source sees it."""
    rho = 1.0 / depth_bhw.to(torch.float32).clamp_min(1e-3)
    band = rho * (float(ratio) - 1.0 / float(ratio))
    seen = span_nbhw > 1e-6
    info = torch.where(seen, (span_nbhw / (shift_nbhw * band).clamp_min(1e-12)) ** 2, torch.zeros_like(span_nbhw))
    total = info.sum(0)
    return torch.where(total > 0, total.clamp_min(1e-30).rsqrt(), torch.full_like(total, math.inf))


def _odometry(kf) -> OdometryCovariance:
    """What the odometry said about itself at a keyframe (``pose_cov_66``, ``twist_cov_66``, ``stamp``)."""
    return OdometryCovariance(pose_66=getattr(kf, 'pose_cov_66', None), twist_66=getattr(kf, 'twist_cov_66', None),
                              stamp=getattr(kf, 'stamp', None))


def window_sigma_planes(ref, sources: Sequence, depth_bhw: torch.Tensor, span_nbhw: torch.Tensor,
                        K_vol_b33: torch.Tensor, model: DriftModel, plane_step_rho: float, *,
                        covariance_only: bool = False, source_sigma: Optional[dict] = None
                        ) -> Tuple[Optional[torch.Tensor], dict]:
    """(B, H, W) std in planes of the measured plane index of a window, and a status dict (items 1-3 of the module
    docstring, all sources).

    ref / sources: keyframes with ``index``, ``stamp``, ``T_world_cam_44``, ``K_b33`` (processing size),
    ``pose_cov_66``, ``twist_cov_66`` and ``twist_world_6``. depth_bhw / span_nbhw: the measurement's depth and each
    source's disparity span (processing pixels) on the volume grid ``K_vol_b33``. plane_step_rho: the plane spacing
    in inverse depth. covariance_only: when no source has a figure from the odometry's covariances
    (:func:`odometry_sigma`), None (the poses count as exact). Status: ``source`` (``covariance`` when every source's
    came from the growth of the pose covariance, ``twist covariance`` when every one came from either covariance
    and some from the twist's, else ``drift``; ``none (...)`` without either in covariance_only), the largest
    per-axis rotation (deg) and translation (mm) std and the median std in planes. source_sigma: per-source
    :class:`PoseSigma` by ``float(stamp)`` (a pose refiner's marginals) used instead of items 1's terms for the
    sources it names (``source`` then says ``window marginals``)."""
    given = source_sigma or {}
    kfs = sorted([ref] + list(sources), key=lambda k: k.index)
    r = kfs.index(ref)
    chains, figures = [], []
    for s in sources:
        i = kfs.index(s)
        chain = kfs[min(i, r):max(i, r) + 1]
        chains.append([k.T_world_cam_44 for k in chain])
        if float(getattr(s, 'stamp', math.nan)) in given:
            figures.append((given[float(s.stamp)], 'window marginals'))
        else:
            figures.append(odometry_sigma(chains[-1], _odometry(chain[0]), _odometry(chain[-1]),
                                          model.cov_trans_per_m))
    kinds = {k for _sig, k in figures}
    if covariance_only and kinds <= {DRIFT}:
        filled = any(getattr(k, 'pose_cov_66', None) is not None or getattr(k, 'twist_cov_66', None) is not None
                     for k in kfs)
        return None, {'source': 'none (the pose covariance does not grow and there is no twist covariance)' if filled
                      else 'none (no odometry covariance)'}
    to_proc = float(ref.K_b33[0, 0, 0] / K_vol_b33[0, 0, 0])     # volume -> processing pixels (as the spans)
    shifts, sig_r, sig_t = [], [], []
    for s, chain, (fig, kind) in zip(sources, chains, figures):
        sig = fig if kind == 'window marginals' else None
        if sig is None:
            first, last = (ref, s) if ref.index <= s.index else (s, ref)
            sig = relative_pose_sigma(model, chain, odom_first=_odometry(first), odom_last=_odometry(last),
                                      twist_ref_6=ref.twist_world_6, twist_src_6=s.twist_world_6)
        sig_r.append(sig.rot_rad)
        sig_t.append(sig.trans_m)
        shifts.append(match_shift_px(depth_bhw, K_vol_b33, sig) * to_proc)
    sigma_planes = inverse_depth_sigma(depth_bhw, span_nbhw, torch.stack(shifts, 0), BAND_RATIO) / plane_step_rho
    source = ('window marginals' if kinds == {'window marginals'} else
              'covariance' if kinds <= {'window marginals', GROWTH} else
              'twist covariance' if kinds <= {'window marginals', GROWTH, TWIST} else 'drift')
    status = {'source': source, 'rot_deg_max': math.degrees(max(sig_r)), 'trans_mm_max': 1000.0 * max(sig_t),
              'median_planes': float(sigma_planes.clamp_max(1e3).median())}
    return sigma_planes, status


def confidence_factor(logp_bdhw: torch.Tensor, depths_d: torch.Tensor, readout: str, ratio: float,
                      sigma_planes_bhw: torch.Tensor) -> torch.Tensor:
    """(B, H, W) in [0, 1]: the ratio confidence of a belief convolved with ``sigma_planes_bhw`` over its plain one
    (1 where the plain one is 0), at the belief's resolution. The estimator multiplies the network's
    full-resolution confidence by it (upsampled): a volume-resolution readout instead of a full-resolution one."""
    depth = dpv_ops.depth_estimate(logp_bdhw, depths_d, readout)
    plain = dpv_ops.ratio_confidence(logp_bdhw, depths_d, depth, ratio)
    widened = dpv_ops.ratio_confidence(logp_bdhw, depths_d, depth, ratio, sigma_planes_bhw)
    return torch.where(plain > 1e-6, widened / plain.clamp_min(1e-6), torch.ones_like(plain)).clamp(0.0, 1.0)


def _blur_matrix(D: int, sigma: float, device, dtype=torch.float32) -> torch.Tensor:
    """(D, D) column-stochastic Gaussian blur over plane index (mass leaving the range is renormalised away)."""
    if sigma <= 0:
        return torch.eye(D, device=device, dtype=dtype)
    i = torch.arange(D, device=device, dtype=dtype)
    M = torch.exp(-0.5 * ((i[:, None] - i[None, :]) / sigma) ** 2)
    return M / M.sum(0, keepdim=True)


def widen_planes(logp_bdhw: torch.Tensor, sigma_planes_bhw: torch.Tensor,
                 ladder: Sequence[float] = WIDTH_LADDER) -> torch.Tensor:
    """Log-probabilities of the DPV convolved per pixel with a Gaussian of ``sigma_planes_bhw`` planes (clamped to
    the ladder's range): the two ladder widths around each pixel's sigma mixed linearly (module docstring, item 4).
    Pixels with sigma 0 are returned unchanged."""
    B, D, H, W = logp_bdhw.shape
    s = sigma_planes_bhw.to(torch.float32).nan_to_num(nan=0.0, posinf=ladder[-1]).clamp(0.0, ladder[-1])
    if not bool((s > 0).any()):
        return logp_bdhw
    p = torch.exp(logp_bdhw.float()).reshape(B, D, H * W)
    lad = torch.tensor(ladder, dtype=torch.float32, device=s.device)
    hi = torch.searchsorted(lad, s.reshape(B, H * W).contiguous(), right=False).clamp(1, len(ladder) - 1)
    lo = hi - 1
    frac = ((s.reshape(B, H * W) - lad[lo]) / (lad[hi] - lad[lo])).clamp(0.0, 1.0)
    out = torch.zeros_like(p)
    for k in range(len(ladder)):
        wk = torch.where(lo == k, 1.0 - frac, torch.zeros_like(frac)) + torch.where(hi == k, frac,
                                                                                     torch.zeros_like(frac))
        if not bool((wk > 0).any()):
            continue
        Mk = _blur_matrix(D, float(ladder[k]), p.device)
        out = out + wk[:, None, :] * torch.einsum('ij,bjn->bin', Mk, p)
    out = out / out.sum(1, keepdim=True).clamp_min(1e-30)
    widened = torch.log(out.clamp_min(1e-30)).reshape(B, D, H, W)
    return torch.where((s > 0)[:, None], widened, logp_bdhw.float())
