"""Metric anchors: points triangulated from matched pixels and metric poses, and the robust fits of a depth map to
them (layer 2).

An anchor is a pixel of the reference view whose depth two views and their metric relative pose fix: the rays
through its two matched pixels meet (midpoint of the common perpendicular), in front of both cameras, with a small
reprojection error in each view and a parallax angle large enough for the depth to be determined. Its depth's
uncertainty is a std of log depth, from two parts:

- independent of the other anchors: the pixel noise of the match, ``sigma_px / f`` radians in each view, moves the
  depth by ``d log z = d(theta) / tan(theta)`` with ``theta`` the parallax angle at the point (the sine rule of the
  triangle reference - source - point, to first order), so ``sigma_ind^2 = 2 (sigma_px / f)^2 / tan(theta)^2``;
- shared by every anchor of the pair: the relative pose's error. Its rotation turns one ray against the other
  (``sigma_rot / tan(theta)``), its translation's length scales every depth of the pair alike
  (``sigma_t / |t|``): ``sigma_pair^2 = sigma_rot^2 / tan(theta)^2 + (sigma_t / |t|)^2``.

The fits take log ratios ``r_i = log z_anchor_i - log z_depth(p_i)`` between the anchors and the depth map at their
pixels:

- :func:`fit_log_scale`: one log scale, the weighted median of the log ratios, each anchor weighted by
  ``1 / (sigma_i^2 + sigma_depth^2)`` (``sigma_depth``: the depth map's own structure error, so that a few very
  precise anchors do not outvote the rest). A median, not a Huber mean: the ratios' contamination is one-sided
  (at object outlines the flow follows the nearer surface), which pulls any mean with it (on a render with exact
  poses a Huber mean sat 1 % nearer than the median). Its std counts the pairs' shared errors, which averaging
  over anchors does not remove; the anchors' Huber weights about it are what the scale map uses.
- :func:`fit_scale_map`: a depth-aware scale map. Anchors gather where there is texture, which is seldom at the
  depth of the texture-free walls and floors nearby, and a network's error depends on depth (a prior-led network
  puts near things too far and far things too near): on the rendered hospital corridor the anchors were right to
  1 %, the network 2-3 % too near at them and right elsewhere, so any scale carried from them across the image by
  position alone made the depth worse. The map is a bilateral grid over (row, column, log depth of the map being
  corrected): each anchor's log ratio is splatted at its position and depth, blurred, and read at every pixel at
  its own position and depth; a pull towards no correction worth a few anchors leaves a pixel without anchors near
  it, in the image and in depth, as the network gave it.
- :func:`widened_confidence`: the probability of the ×ratio band after an extra log-depth error of std ``sigma``:
  the confidence read as that of a zero-mean Gaussian log error, its variance increased by ``sigma^2``.

Conventions: ``T_b_a`` maps points of view a to view b; pixels (x, y) at the size ``K_33`` belongs to; depths are
z in metres. numpy only; no ROS, no torch.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict, Optional, Tuple

import cv2
import numpy as np
from scipy.ndimage import convolve1d
from scipy.special import erf, erfinv

__all__ = ['AnchorConfig', 'Anchors', 'ScaleFit', 'ScaleMap', 'triangulate_pair', 'triangulate_track',
           'concat_anchors', 'fit_log_scale', 'fit_scale_map', 'widened_confidence', 'sample_depth',
           'depth_edge_mask', 'weighted_median', 'refine_tracks', 'confidence_sigma', 'band_confidence',
           'blend_log_depth', 'axis_readback']


@dataclass(frozen=True)
class AnchorConfig:
    """pixel_sigma_px: the std of a match's position (pixels, each view); min_parallax_deg: anchors whose rays meet
    at a smaller angle are dropped (their depth is not determined); max_reprojection_px: the largest reprojection
    error in either view; max_sigma_log: anchors less precise than this (std of log depth) are dropped;
    min_depth_m / max_depth_m: anchors outside are dropped; depth_sigma_log: the depth map's own error at a
    pixel (std of log depth) added to each anchor's in the fits; huber_k: the fits' Huber threshold (in stds);
    min_anchors: fewer usable anchors give no fit; min_consistent_fraction: a pair or
    track set whose poses reproject fewer than this share of its matches (in front, with parallax) within
    ``max_reprojection_px`` is dropped whole (the poses do not explain the images: the few matches that fit them
    by chance are a biased sample, not anchors); grid_rows / grid_cols / grid_depth_bins: nodes of the scale
    map's bilateral grid over the image and over log depth (between the depth planes' nearest and farthest);
    grid_prior_anchors: how many anchors' weight the map's pull towards no correction is worth (fewer anchors near
    a pixel, in the image and in depth, move it less than halfway); bias_sigma_log: the std of an anchor set's
    systematic error, shared by all of a keyframe's anchors (measured on the rendered sequences with exact poses:
    the keyframes' median anchor / true depth spreads by a few percent, with tails to 10-20 % where the flow and
    the tracker agree on a wrong match); correction_sigmas: the depth moves only by as much as it disagrees with
    its anchors beyond this many of their stds (a soft threshold: a check, then a correction);
    edge_log_range: anchors where the depth map's log depth spans more than this over the 3x3 pixels around them
    are not compared with it (a depth edge: textured pixels gather on object outlines, where the flow follows the
    nearer surface and the map's pixel may hold the farther one); max_inverse_depth_ratio: a track whose inverse
    distance is more than this factor from the set's median is dropped (optical flow that fails on a large
    displacement stays near zero, which triangulates far behind the scene, or overshoots: on the rendered hospital
    corridor such tracks put whole keyframes' anchors at 2 to 70 times the true depth); min_inlier_fraction: a fit
    whose anchors agree with one scale (within huber_k of their sigma) in a smaller share is not applied (they do not
    tell one story); track_window_px / track_levels / track_fb_px: each track's pixel in every other view is refined
    by pyramidal Lucas-Kanade from the reference image (window of this size, pyramid levels above the image, started
    at the chained flow's guess) and kept only
    where tracking back lands within ``track_fb_px`` of where it started (dense flow chained over keyframes
    accumulates its error and underestimates large displacements: on the rendered hospital corridor its anchors sat
    3-12 % too far on keyframes whose network depth was right); max_tracks: at most this many tracks a keyframe
    (evenly spread over the flow's sampled pixels): the tracking is most of the anchors' time."""
    pixel_sigma_px: float = 0.5
    min_parallax_deg: float = 1.0
    max_reprojection_px: float = 1.5
    max_sigma_log: float = 0.1
    min_depth_m: float = 0.05
    max_depth_m: float = 100.0
    depth_sigma_log: float = 0.1
    huber_k: float = 1.5
    min_anchors: int = 20
    min_consistent_fraction: float = 0.5
    edge_log_range: float = 0.1
    max_inverse_depth_ratio: float = 4.0
    track_window_px: int = 9
    track_levels: int = 1
    max_tracks: int = 500
    track_fb_px: float = 0.5
    min_inlier_fraction: float = 0.5
    grid_rows: int = 6
    grid_cols: int = 8
    grid_depth_bins: int = 8
    grid_prior_anchors: float = 2.0
    bias_sigma_log: float = 0.03
    correction_sigmas: float = 1.0

    def __post_init__(self):
        for name in ('pixel_sigma_px', 'max_reprojection_px', 'max_sigma_log', 'depth_sigma_log', 'huber_k',
                     'bias_sigma_log', 'grid_prior_anchors'):
            if not getattr(self, name) > 0:
                raise ValueError(f'{name} must be > 0, not {getattr(self, name)}')
        if not 0 <= self.min_parallax_deg < 90:
            raise ValueError(f'min_parallax_deg must be in [0, 90), not {self.min_parallax_deg}')
        if not 0 < self.min_depth_m < self.max_depth_m:
            raise ValueError(f'need 0 < min_depth_m < max_depth_m, not {self.min_depth_m}, {self.max_depth_m}')
        if self.min_anchors < 1 or min(self.grid_cols, self.grid_rows, self.grid_depth_bins) < 2:
            raise ValueError('min_anchors must be >= 1 and grid_rows, grid_cols, grid_depth_bins >= 2')


@dataclass
class Anchors:
    """Anchors of one reference view. uv_n2: their pixels in the reference (at the size K_33 belongs to); depth_n:
    z in the reference (m); sigma_ind_n / sigma_pair_n: the independent and the shared std of log depth (module
    doc); pair_n: which pair made each (an index); rejected: candidates dropped, by reason ('lost' (a view where
    the track was not found), 'behind', 'atypical'
    (an inverse distance far from the set's median), 'parallax',
    'reprojection', 'inconsistent_poses' (every match that fitted poses that most matches of their pair do not),
    'sigma', 'range')."""
    uv_n2: np.ndarray
    depth_n: np.ndarray
    sigma_ind_n: np.ndarray
    sigma_pair_n: np.ndarray
    pair_n: np.ndarray
    K_33: np.ndarray
    rejected: Dict[str, int] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(len(self.depth_n))

    @property
    def sigma_n(self) -> np.ndarray:
        """Each anchor's whole std of log depth."""
        return np.hypot(self.sigma_ind_n, self.sigma_pair_n)

    @staticmethod
    def empty(K_33: Optional[np.ndarray] = None) -> 'Anchors':
        z = np.zeros(0)
        return Anchors(np.zeros((0, 2)), z, z.copy(), z.copy(), np.zeros(0, np.int64),
                       np.eye(3) if K_33 is None else np.asarray(K_33, np.float64))


def _rays(p_n2: np.ndarray, K_33: np.ndarray) -> np.ndarray:
    x = np.c_[p_n2, np.ones(len(p_n2))] @ np.linalg.inv(K_33).T
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def _project(X_n3: np.ndarray, K_33: np.ndarray) -> np.ndarray:
    p = X_n3 @ K_33.T
    return p[:, :2] / p[:, 2:3]


def refine_tracks(gray_ref: np.ndarray, p_ref_n2: np.ndarray, gray_v: np.ndarray, guess_n2: np.ndarray,
                  config: AnchorConfig = AnchorConfig()) -> np.ndarray:
    """The reference pixels ``p_ref_n2`` found in another view (grey uint8 images of one size) by pyramidal
    Lucas-Kanade started at ``guess_n2``, checked by tracking back: (n, 2), NaN where a guess was NaN, the tracker
    lost the point, or the way back misses the start by more than ``track_fb_px``."""
    out = np.full((len(p_ref_n2), 2), np.nan)
    valid = np.all(np.isfinite(p_ref_n2), axis=1) & np.all(np.isfinite(guess_n2), axis=1)
    if not valid.any():
        return out
    win = (int(config.track_window_px), int(config.track_window_px))
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.01)
    p0 = np.ascontiguousarray(p_ref_n2[valid], np.float32)
    lev = int(config.track_levels)
    p1, st, _ = cv2.calcOpticalFlowPyrLK(gray_ref, gray_v, p0, np.ascontiguousarray(guess_n2[valid], np.float32),
                                         winSize=win, maxLevel=lev, criteria=crit, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    back, st2, _ = cv2.calcOpticalFlowPyrLK(gray_v, gray_ref, p1, p0.copy(), winSize=win, maxLevel=lev,
                                            criteria=crit, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    good = (st.ravel() == 1) & (st2.ravel() == 1) & (np.linalg.norm(back - p0, axis=1) <= config.track_fb_px)
    idx = np.flatnonzero(valid)
    out[idx[good]] = p1[good]
    return out


def triangulate_pair(p_ref_n2: np.ndarray, p_src_n2: np.ndarray, K_33: np.ndarray, T_src_ref_44: np.ndarray,
                     sigma_rot_rad: float = 0.0, sigma_trans_m: float = 0.0, pair: int = 0,
                     config: AnchorConfig = AnchorConfig()) -> Anchors:
    """Anchors in the reference from matched pixels ``p_ref_n2`` (reference) and ``p_src_n2`` (source), both at the
    size of ``K_33``, and the metric relative pose ``T_src_ref_44``; ``sigma_rot_rad`` / ``sigma_trans_m``: the
    std of that pose's rotation (per axis) and translation (along it), shared by every anchor of the pair."""
    T_ref_src = np.linalg.inv(np.asarray(T_src_ref_44, np.float64))
    return triangulate_track([p_ref_n2, p_src_n2], [np.eye(4), T_ref_src], K_33, 0, sigma_rot_rad, sigma_trans_m,
                             pair, config)


def triangulate_track(points_v, T_world_cam_v, K_33: np.ndarray, ref_view: int, sigma_rot_rad: float = 0.0,
                      sigma_trans_m: float = 0.0, pair: int = 0, config: AnchorConfig = AnchorConfig()) -> Anchors:
    """Anchors in view ``ref_view`` from tracks over several views: ``points_v[v]`` (n, 2) the pixels of the n
    tracks in view v (NaN where a track is not seen), ``T_world_cam_v[v]`` the views' metric poses, one ``K_33``.
    Each track is triangulated from its first and last views (the longest baseline: rays' midpoint) and kept only
    where it lies in front of both, reprojects within ``max_reprojection_px`` in every view and has the parallax and
    precision the config asks (both judged at the set's typical distance, not at the track's own triangulated one,
    which would select the matches whose noise enlarges their parallax); its pixel in the reference is the one
    measured there. ``sigma_rot_rad`` /
    ``sigma_trans_m``: the std of the first-to-last relative pose (rotation per axis, translation), shared."""
    K = np.asarray(K_33, np.float64)
    P = [np.asarray(p, np.float64).reshape(-1, 2) for p in points_v]
    T = [np.asarray(t, np.float64) for t in T_world_cam_v]
    n = len(P[ref_view])
    rejected = {'lost': 0, 'behind': 0, 'parallax': 0, 'reprojection': 0, 'sigma': 0, 'range': 0}
    first, last = 0, len(P) - 1
    T_l_f = np.linalg.inv(T[last]) @ T[first]
    R_lf, t_lf = T_l_f[:3, :3], T_l_f[:3, 3]
    c = -R_lf.T @ t_lf                          # the last view's centre in the first view
    baseline = float(np.linalg.norm(c))
    seen = np.all([np.all(np.isfinite(p), axis=1) for p in P], axis=0)
    if n == 0 or baseline <= 0.0:
        out = Anchors.empty(K)
        out.rejected = dict(rejected, parallax=n)
        return out
    pf = np.where(seen[:, None], P[first], 0.0)
    pl = np.where(seen[:, None], P[last], 0.0)
    da = _rays(pf, K)
    db = _rays(pl, K) @ R_lf                    # the last view's rays, turned into the first (R^T d per row)
    # closest points of the rays  la * da  and  c + lb * db
    b = np.einsum('ij,ij->i', da, db)
    d1, d2 = da @ c, db @ c
    den = 1.0 - b * b
    with np.errstate(divide='ignore', invalid='ignore'):
        la = (d1 - b * d2) / den
        lb = (b * d1 - d2) / den
    X_f = 0.5 * (la[:, None] * da + (c[None] + lb[:, None] * db))
    front = seen & np.isfinite(la) & np.isfinite(lb) & (la > 0) & (lb > 0)
    X_w = X_f @ T[first][:3, :3].T + T[first][:3, 3]
    err = np.zeros(n)
    for v in range(len(P)):
        T_cw = np.linalg.inv(T[v])
        X_v = X_w @ T_cw[:3, :3].T + T_cw[:3, 3]
        front &= X_v[:, 2] > 0
        with np.errstate(divide='ignore', invalid='ignore'):
            err = np.fmax(err, np.linalg.norm(_project(X_v, K) - P[v], axis=1))
        if v == ref_view:
            z = X_v[:, 2]
    rejected['lost'] = int((~seen).sum())
    rejected['behind'] = int((seen & ~front).sum())
    rejected['atypical'] = 0
    # the parallax each track would have at the set's typical distance (the median of the signed inverse distances
    # of every seen track, which match noise leaves unbiased): selecting on each track's own measured parallax
    # would keep the matches whose error happens to enlarge it, i.e. depths biased near
    inv = 1.0 / la[seen & np.isfinite(la)]
    inv_med = float(np.median(inv)) if inv.size else 0.0
    X_typ = da / max(inv_med, 1e-9)
    ray_b = X_typ - c
    ray_b = ray_b / np.maximum(np.linalg.norm(ray_b, axis=1, keepdims=True), 1e-12)
    theta = np.arccos(np.clip(np.einsum('ij,ij->i', da, ray_b), -1.0, 1.0))
    if not inv_med > 0:
        theta[:] = 0.0
    with np.errstate(divide='ignore', invalid='ignore'):
        inv_all = 1.0 / la
    typical = (inv_all * config.max_inverse_depth_ratio >= inv_med) & (inv_all <= config.max_inverse_depth_ratio *
                                                                       inv_med)
    rejected['atypical'] = int((front & ~typical).sum())
    ok = front & typical
    par = ok & (theta >= math.radians(config.min_parallax_deg)) & (theta > 0)
    rejected['parallax'] = int((ok & ~par).sum())
    ok = par
    rep = ok & (err <= config.max_reprojection_px)
    rejected['reprojection'] = int((ok & ~rep).sum())
    if rep.sum() < config.min_consistent_fraction * ok.sum():
        rejected['inconsistent_poses'] = int(rep.sum())
        rep[:] = False
    ok = rep
    f = 0.5 * (K[0, 0] + K[1, 1])
    with np.errstate(divide='ignore', invalid='ignore'):
        tan_t = np.tan(theta)
        sigma_ind = math.sqrt(2.0) * (config.pixel_sigma_px / f) / tan_t
        sigma_pair = np.sqrt((sigma_rot_rad / tan_t) ** 2 + (sigma_trans_m / baseline) ** 2)
    sig = ok & (np.hypot(sigma_ind, sigma_pair) <= config.max_sigma_log)
    rejected['sigma'] = int((ok & ~sig).sum())
    ok = sig
    rng = ok & (z >= config.min_depth_m) & (z <= config.max_depth_m)
    rejected['range'] = int((ok & ~rng).sum())
    ok = rng
    return Anchors(P[ref_view][ok], z[ok], sigma_ind[ok], sigma_pair[ok], np.full(int(ok.sum()), pair, np.int64),
                   K, rejected)


def concat_anchors(parts) -> Anchors:
    """One set from several pairs' anchors of the same reference (the first's ``K_33``; each part's pixels are
    brought to it through normalised coordinates); rejected counts add up."""
    parts = list(parts)
    if not parts:
        return Anchors.empty()
    K = parts[0].K_33
    uv, rejected = [], {}
    for a in parts:
        x = np.c_[a.uv_n2, np.ones(len(a))] @ np.linalg.inv(a.K_33).T @ K.T
        uv.append(x[:, :2])
        for k, v in a.rejected.items():
            rejected[k] = rejected.get(k, 0) + int(v)
    return Anchors(np.concatenate(uv).reshape(-1, 2), np.concatenate([a.depth_n for a in parts]),
                   np.concatenate([a.sigma_ind_n for a in parts]), np.concatenate([a.sigma_pair_n for a in parts]),
                   np.concatenate([a.pair_n for a in parts]), K, rejected)


def depth_edge_mask(depth_hw: np.ndarray, log_range: float) -> np.ndarray:
    """True where the log depth spans more than ``log_range`` over a pixel's 3x3 neighbourhood, or where a
    neighbour has no depth."""
    d = np.asarray(depth_hw, np.float32)
    good = np.isfinite(d) & (d > 0)
    logd = np.log(np.where(good, d, 1.0)).astype(np.float32)
    kernel = np.ones((3, 3), np.uint8)
    span = cv2.dilate(logd, kernel) - cv2.erode(logd, kernel)
    holes = cv2.erode(good.astype(np.uint8), kernel) == 0
    return (span > log_range) | holes


def sample_depth(depth_hw: np.ndarray, uv_n2: np.ndarray) -> np.ndarray:
    """Bilinear depth at sub-pixel positions (x, y) of a depth map (NaN or <= 0: no depth); NaN where a corner has
    none or the position is outside."""
    d = np.asarray(depth_hw, np.float64)
    H, W = d.shape
    x, y = uv_n2[:, 0], uv_n2[:, 1]
    inside = (x >= 0) & (x <= W - 1) & (y >= 0) & (y <= H - 1)
    x0 = np.clip(np.floor(x), 0, max(W - 2, 0)).astype(np.int64)
    y0 = np.clip(np.floor(y), 0, max(H - 2, 0)).astype(np.int64)
    x1, y1 = np.minimum(x0 + 1, W - 1), np.minimum(y0 + 1, H - 1)
    fx, fy = np.clip(x - x0, 0, 1), np.clip(y - y0, 0, 1)
    corners = np.stack([d[y0, x0], d[y0, x1], d[y1, x0], d[y1, x1]], 1)
    good = np.all(np.isfinite(corners) & (corners > 0), axis=1) & inside
    out = ((1 - fx) * (1 - fy) * corners[:, 0] + fx * (1 - fy) * corners[:, 1] + (1 - fx) * fy * corners[:, 2]
           + fx * fy * corners[:, 3])
    return np.where(good, out, np.nan)


@dataclass
class ScaleFit:
    """A robust fit of one log scale: log_scale (add it to log depth), its std (sigma), the anchors used, the
    inliers (Huber weight 1) among them, and each used anchor's final weight (IRLS, 0 for anchors not used)."""
    log_scale: float
    sigma: float
    used: int
    inliers: int
    weight_n: np.ndarray

    @property
    def scale(self) -> float:
        return math.exp(self.log_scale)


def _huber_weights(r: np.ndarray, s: np.ndarray, k: float) -> np.ndarray:
    a = np.abs(r) / s
    return np.where(a <= k, 1.0, k / np.maximum(a, 1e-12))


def weighted_median(x_n: np.ndarray, w_n: np.ndarray) -> float:
    """The value below which half of the total weight lies (the midpoint where it falls exactly between two)."""
    order = np.argsort(x_n)
    x, w = np.asarray(x_n, np.float64)[order], np.asarray(w_n, np.float64)[order]
    c = np.cumsum(w)
    half = 0.5 * c[-1]
    i = int(np.searchsorted(c, half))
    if i < len(x) - 1 and math.isclose(c[i], half, rel_tol=1e-12):
        return 0.5 * (x[i] + x[i + 1])
    return float(x[i])


def fit_log_scale(log_ratio_n: np.ndarray, anchors: Anchors, config: AnchorConfig = AnchorConfig()
                  ) -> Optional[ScaleFit]:
    """The log scale that takes the depth to the anchors (module doc); None with fewer than ``min_anchors``
    finite ratios. ``log_ratio_n``: ``log z_anchor - log z_depth`` per anchor (NaN: no depth there)."""
    r = np.asarray(log_ratio_n, np.float64)
    use = np.isfinite(r)
    if int(use.sum()) < config.min_anchors:
        return None
    s = np.sqrt(anchors.sigma_ind_n ** 2 + anchors.sigma_pair_n ** 2 + config.depth_sigma_log ** 2)[use]
    ru = r[use]
    mu = weighted_median(ru, 1.0 / s ** 2)
    w = _huber_weights(ru - mu, s, config.huber_k) / s ** 2
    inliers = int((np.abs(ru - mu) <= config.huber_k * s).sum())
    # independent part: the weighted median's std (pi / 2 times the weighted mean's variance); shared part: each
    # pair's pose error, averaged over the pairs with the share of the weight each pair has
    var_ind = 0.5 * math.pi / float(np.sum(1.0 / s ** 2))
    pairs = anchors.pair_n[use]
    var_pair = 0.0
    total = float(np.sum(w))
    for p in np.unique(pairs):
        m = pairs == p
        share = float(np.sum(w[m])) / total
        var_pair += (share * float(np.median(anchors.sigma_pair_n[use][m]))) ** 2
    weight = np.zeros(len(r))
    weight[use] = w
    return ScaleFit(mu, math.sqrt(var_ind + var_pair), int(use.sum()), inliers, weight)


@dataclass
class ScaleMap:
    """A depth-aware log-scale map at every pixel of a depth map (H, W): the correction (add it to log depth), its
    std, and the anchors' weight that supports it (0: no anchor near in the image and in depth)."""
    log_scale_hw: np.ndarray
    sigma_hw: np.ndarray
    support_hw: np.ndarray


def _grid_coords(uv_n2: np.ndarray, log_d_n: np.ndarray, size_hw: Tuple[int, int], shape: Tuple[int, int, int],
                 log_range: Tuple[float, float]) -> np.ndarray:
    """Continuous (row, col, bin) coordinates in a bilateral grid of ``shape`` (rows, cols, bins): nodes at the
    centres of a rows x cols tiling of the image (OpenCV's resize convention) and of ``bins`` equal steps of log
    depth over ``log_range``; clamped to the grid."""
    H, W = size_hw
    rows, cols, bins = shape
    gy = np.clip((uv_n2[:, 1] + 0.5) / H * rows - 0.5, 0, rows - 1)
    gx = np.clip((uv_n2[:, 0] + 0.5) / W * cols - 0.5, 0, cols - 1)
    lo, hi = log_range
    gz = np.clip((log_d_n - lo) / max(hi - lo, 1e-9) * (bins - 1), 0, bins - 1)
    return np.stack([gy, gx, gz], 1)


def _corners(c_n3: np.ndarray, shape: Tuple[int, int, int]):
    """The 8 trilinear corners of grid coordinates: (flat indices (n, 8), weights (n, 8))."""
    lo = np.floor(c_n3).astype(np.int64)
    lo = np.minimum(lo, np.maximum(np.asarray(shape) - 2, 0))
    f = c_n3 - lo
    idx, wts = [], []
    for dy in (0, 1):
        for dx in (0, 1):
            for dz in (0, 1):
                y = np.minimum(lo[:, 0] + dy, shape[0] - 1)
                x = np.minimum(lo[:, 1] + dx, shape[1] - 1)
                z = np.minimum(lo[:, 2] + dz, shape[2] - 1)
                idx.append((y * shape[1] + x) * shape[2] + z)
                wts.append((f[:, 0] if dy else 1 - f[:, 0]) * (f[:, 1] if dx else 1 - f[:, 1])
                           * (f[:, 2] if dz else 1 - f[:, 2]))
    return np.stack(idx, 1), np.stack(wts, 1)


def _splat_blur(idx: np.ndarray, wts: np.ndarray, values_n: np.ndarray, shape) -> np.ndarray:
    """Trilinear splat of per-point values into the grid, then a [1 2 1] / 4 blur along each axis."""
    g = np.bincount(idx.ravel(), (wts * values_n[:, None]).ravel(), minlength=int(np.prod(shape)))
    g = g.reshape(shape)
    for axis in range(3):
        g = convolve1d(g, [0.25, 0.5, 0.25], axis=axis, mode='nearest')
    return g


def _slice(grid: np.ndarray, idx: np.ndarray, wts: np.ndarray) -> np.ndarray:
    return np.sum(grid.ravel()[idx] * wts, axis=1)


def _slice_image(grids: np.ndarray, gz_hw: np.ndarray, size_hw: Tuple[int, int]) -> np.ndarray:
    """Grids (rows, cols, bins, channels) read at every pixel of an image of ``size_hw`` at its bin coordinate
    ``gz_hw``: (channels, H, W). Each bin's plane is resized to the image (bilinear, the nodes at the cells'
    centres: :func:`_grid_coords`' convention), then the two bins around a pixel's are mixed linearly: the same as
    trilinear slicing, at a fraction of its cost."""
    H, W = size_hw
    rows, cols, bins, ch = grids.shape
    gz = np.asarray(gz_hw, np.float32)
    out = np.zeros((ch, H, W), np.float32)
    for z in range(bins):
        tent = np.maximum(0.0, 1.0 - np.abs(gz - np.float32(z)))       # the linear weight of bin z at each pixel
        if not tent.any():
            continue
        plane = cv2.resize(np.ascontiguousarray(grids[:, :, z, :], np.float32), (W, H),
                           interpolation=cv2.INTER_LINEAR).reshape(H, W, ch)
        out += np.moveaxis(plane, -1, 0) * tent
    return out.astype(np.float64)


def axis_readback(g: np.ndarray, n: int) -> np.ndarray:
    """What the grid gives back, along one axis of ``n`` nodes, of a unit weight splatted at grid coordinate ``g``
    and read at the same coordinate: ``s^T B s`` with ``s`` the two linear splat weights and ``B`` the [1 2 1] / 4
    blur whose ends repeat the end node (``mode='nearest'``). 1/2 at an interior node, 3/8 half way between two,
    3/4 at an end node; the product over the three axes is the share of an anchor's weight read back at its own
    position (about 1/14 on average inside the grid, up to 0.42 in its corners)."""
    g = np.asarray(g, np.float64)
    if n == 1:
        return np.ones_like(g)
    B = np.zeros((n, n))
    for i in range(n):
        B[i, i] += 0.5
        B[i, max(i - 1, 0)] += 0.25
        B[i, min(i + 1, n - 1)] += 0.25
    lo = np.minimum(np.floor(g).astype(np.int64), n - 2)
    f = g - lo
    return (1 - f) ** 2 * B[lo, lo] + 2 * f * (1 - f) * B[lo, lo + 1] + f ** 2 * B[lo + 1, lo + 1]


def fit_scale_map(log_ratio_n: np.ndarray, anchors: Anchors, uv_n2: np.ndarray, depth_hw: np.ndarray,
                  fit: ScaleFit, log_range: Tuple[float, float], config: AnchorConfig = AnchorConfig(),
                  in_anchor_weights: bool = False) -> ScaleMap:
    """The depth-aware scale map (module doc) of a depth map from its anchors at pixels ``uv_n2`` of it and their
    log ratios: a bilateral grid over (row, column, log depth of the map) in which each anchor's log ratio is
    splatted with its weight ``1 / (sigma_i^2 + sigma_depth^2)``, blurred, and read at every pixel at its own
    position and depth; robust (Huber weights about a first pass) and pulled towards no correction by a prior worth
    ``grid_prior_anchors`` anchors, so that a region or a depth without anchors nearby keeps the network's depth.
    ``log_range``: the log depths the grid spans (the depth planes'); ``fit``: the global fit (its std, mostly the
    pairs' shared pose error, is added to every pixel's).

    By default the support is what the grid reads back, a fraction of the anchors' own weights (a lone anchor's
    read at its own pixel is 1/8 of it at a node, about 1/14 on average), so the prior outweighs each anchor several
    times over: a cautious correction. ``in_anchor_weights``: the support divided by what the grid gives back at
    each position (:func:`axis_readback` over the three axes, at the anchors and at every pixel), so it counts the
    anchors' own weights (an anchor at the pixel counts whole, one a cell away about half), and no pull towards no
    correction: the map is the kernel-weighted mean of the anchors near and its σ that mean's (infinite without
    anchors near): the map that judges whether a region disagrees with its anchors."""
    shape = (config.grid_rows, config.grid_cols, config.grid_depth_bins)
    d = np.asarray(depth_hw, np.float64)
    H, W = d.shape
    r = np.asarray(log_ratio_n, np.float64)
    use = np.isfinite(r)
    s = np.sqrt(anchors.sigma_ind_n ** 2 + anchors.sigma_pair_n ** 2 + config.depth_sigma_log ** 2)[use]
    with np.errstate(divide='ignore', invalid='ignore'):
        log_d_anchor = np.log(sample_depth(d, uv_n2[use]))
    ok = np.isfinite(log_d_anchor)
    ru, s, log_d_anchor, uv = r[use][ok], s[ok], log_d_anchor[ok], uv_n2[use][ok]
    coords = _grid_coords(uv, log_d_anchor, (H, W), shape, log_range)
    a_idx, a_wts = _corners(coords, shape)
    w_prior = 0.0 if in_anchor_weights else config.grid_prior_anchors / config.depth_sigma_log ** 2
    w = 1.0 / s ** 2
    for _ in range(2):                      # a first pass, then Huber weights about what it says at each anchor
        Wg = _splat_blur(a_idx, a_wts, w, shape)
        WRg = _splat_blur(a_idx, a_wts, w * ru, shape)
        local = _slice(WRg, a_idx, a_wts) / (_slice(Wg, a_idx, a_wts) + w_prior)
        w = _huber_weights(ru - local, s, config.huber_k) / s ** 2
    Wg = _splat_blur(a_idx, a_wts, w, shape)
    WRg = _splat_blur(a_idx, a_wts, w * ru, shape)
    good = np.isfinite(d) & (d > 0)
    lo, hi = log_range
    gz = np.clip((np.log(np.where(good, d, 1.0)) - lo) / max(hi - lo, 1e-9) * (shape[2] - 1), 0, shape[2] - 1)
    support, wr = _slice_image(np.stack([Wg, WRg], -1), gz, (H, W))
    if in_anchor_weights:
        gy = np.clip((np.arange(H) + 0.5) / H * shape[0] - 0.5, 0, shape[0] - 1)
        gx = np.clip((np.arange(W) + 0.5) / W * shape[1] - 0.5, 0, shape[1] - 1)
        back = (axis_readback(gy, shape[0])[:, None] * axis_readback(gx, shape[1])[None, :]
                * axis_readback(gz, shape[2]))
        support, wr = support / back, wr / back
    with np.errstate(divide='ignore', invalid='ignore'):
        g = np.where(support + w_prior > 0, wr / (support + w_prior), 0.0)
        sigma = np.sqrt(1.0 / (support + w_prior) + fit.sigma ** 2)
    return ScaleMap(np.where(good, g, 0.0), sigma, support)


def confidence_sigma(conf: np.ndarray, ratio: float = 1.25) -> np.ndarray:
    """The std of a zero-mean Gaussian log-depth error whose ×ratio band holds probability ``conf``:
    ``log(ratio) / (sqrt 2 erfinv(conf))`` (infinite at 0, 0 at 1)."""
    c = np.clip(np.asarray(conf, np.float64), 0.0, 1.0 - 1e-9)
    with np.errstate(divide='ignore'):
        return math.log(ratio) / (math.sqrt(2.0) * np.maximum(erfinv(c), 1e-12))


def band_confidence(sigma_log: np.ndarray, ratio: float = 1.25) -> np.ndarray:
    """The probability of the ×ratio band of a zero-mean Gaussian log-depth error of std ``sigma_log`` (the inverse
    of :func:`confidence_sigma`)."""
    with np.errstate(divide='ignore'):
        return erf(math.log(ratio) / (math.sqrt(2.0) * np.asarray(sigma_log, np.float64)))


def widened_confidence(conf: np.ndarray, sigma_log, ratio: float = 1.25) -> np.ndarray:
    """The probability of the ×ratio band once an independent log-depth error of std ``sigma_log`` (scalar or per
    pixel) is added: the confidence ``c`` read as ``P(|e| < log ratio)`` of a zero-mean Gaussian ``e``, whose
    variance is then increased by ``sigma_log^2``. A confidence of 1 stays 1 only with sigma 0; 0 stays 0."""
    c = np.clip(np.asarray(conf, np.float64), 0.0, 1.0 - 1e-9)
    s = np.sqrt(confidence_sigma(c, ratio) ** 2 + np.asarray(sigma_log, np.float64) ** 2)
    return np.where(c > 0, band_confidence(s, ratio), 0.0)


def blend_log_depth(depth_a: np.ndarray, conf_a: np.ndarray, depth_b: np.ndarray, conf_b: np.ndarray,
                    ratio: float = 1.25) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two depth estimates of the same pixels, each with its confidence: (depth, confidence, weight of b). The
    depth is the inverse-variance mean in log depth, each confidence read as a Gaussian log error's std
    (:func:`confidence_sigma`). Its std is the smaller of the two (no credit for combining them: their errors need
    not be independent) widened by the spread of the two-point mixture, ``w_a w_b (log d_a - log d_b)^2`` in
    variance: two confident estimates that disagree give a blend nobody is sure of. A confidence of 0 gives its
    estimate no weight."""
    sa = confidence_sigma(conf_a, ratio)
    sb = confidence_sigma(conf_b, ratio)
    with np.errstate(divide='ignore', over='ignore'):
        wa = np.where(np.asarray(conf_a) > 0, 1.0 / sa ** 2, 0.0)
        wb = np.where(np.asarray(conf_b) > 0, 1.0 / sb ** 2, 0.0)
    total = wa + wb
    w_b = np.where(total > 0, wb / np.where(total > 0, total, 1.0), 0.0)
    with np.errstate(divide='ignore', invalid='ignore'):
        gap = np.log(depth_b) - np.log(depth_a)
        log_d = np.log(depth_a) + w_b * gap
        spread = np.where(w_b * (1.0 - w_b) > 0, w_b * (1.0 - w_b) * gap ** 2, 0.0)
    conf = np.where(spread > 0, band_confidence(np.sqrt(np.minimum(sa, sb) ** 2 + spread), ratio),
                    np.maximum(conf_a, conf_b))
    return np.exp(log_d), conf, w_b
