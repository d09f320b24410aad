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

- :func:`fit_log_scale`: one log scale by iteratively reweighted least squares with Huber weights, each anchor
  weighted by ``1 / (sigma_i^2 + sigma_depth^2)`` (``sigma_depth``: the depth map's own structure error, so that a
  few very precise anchors do not outvote the rest); its std counts the pairs' shared errors, which averaging over
  anchors does not remove.
- :func:`fit_scale_grid`: a smooth log-scale map on a coarse grid over the image (bilinear interpolation of the
  grid's nodes), least squares on the anchors' log ratios (their Huber weights from the global fit) plus a
  smoothness term between neighbouring nodes and a pull towards the global log scale where the anchors say
  nothing: a Gaussian Markov random field of a few dozen unknowns, solved exactly; each node's posterior std comes
  with it.
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
from scipy.special import erf, erfinv

__all__ = ['AnchorConfig', 'Anchors', 'ScaleFit', 'ScaleGrid', 'triangulate_pair', 'triangulate_track',
           'concat_anchors', 'fit_log_scale', 'fit_scale_grid', 'grid_log_scale_at', 'grid_dense',
           'widened_confidence', 'sample_depth']


@dataclass(frozen=True)
class AnchorConfig:
    """pixel_sigma_px: the std of a match's position (pixels, each view); min_parallax_deg: anchors whose rays meet
    at a smaller angle are dropped (their depth is not determined); max_reprojection_px: the largest reprojection
    error in either view; max_sigma_log: anchors less precise than this (std of log depth) are dropped;
    min_depth_m / max_depth_m: anchors outside are dropped; depth_sigma_log: the depth map's own error at a
    pixel (std of log depth) added to each anchor's in the fits; huber_k: the fits' Huber threshold (in stds);
    iterations: IRLS iterations; min_anchors: fewer usable anchors give no fit; min_consistent_fraction: a pair or
    track set whose poses reproject fewer than this share of its matches (in front, with parallax) within
    ``max_reprojection_px`` is dropped whole (the poses do not explain the images: the few matches that fit them
    by chance are a biased sample, not anchors); grid_cols / grid_rows: nodes of
    the scale map; grid_smoothness: std of the log-scale difference between neighbouring nodes;
    grid_prior_sigma: std of a node's departure from the global log scale where no anchor speaks."""
    pixel_sigma_px: float = 0.5
    min_parallax_deg: float = 1.0
    max_reprojection_px: float = 1.5
    max_sigma_log: float = 0.1
    min_depth_m: float = 0.05
    max_depth_m: float = 100.0
    depth_sigma_log: float = 0.1
    huber_k: float = 1.5
    iterations: int = 10
    min_anchors: int = 20
    min_consistent_fraction: float = 0.5
    grid_cols: int = 8
    grid_rows: int = 6
    grid_smoothness: float = 0.15
    grid_prior_sigma: float = 0.3

    def __post_init__(self):
        for name in ('pixel_sigma_px', 'max_reprojection_px', 'max_sigma_log', 'depth_sigma_log', 'huber_k',
                     'grid_smoothness', 'grid_prior_sigma'):
            if not getattr(self, name) > 0:
                raise ValueError(f'{name} must be > 0, not {getattr(self, name)}')
        if not 0 <= self.min_parallax_deg < 90:
            raise ValueError(f'min_parallax_deg must be in [0, 90), not {self.min_parallax_deg}')
        if not 0 < self.min_depth_m < self.max_depth_m:
            raise ValueError(f'need 0 < min_depth_m < max_depth_m, not {self.min_depth_m}, {self.max_depth_m}')
        if self.iterations < 1 or self.min_anchors < 1 or self.grid_cols < 1 or self.grid_rows < 1:
            raise ValueError('iterations, min_anchors, grid_cols and grid_rows must be >= 1')


@dataclass
class Anchors:
    """Anchors of one reference view. uv_n2: their pixels in the reference (at the size K_33 belongs to); depth_n:
    z in the reference (m); sigma_ind_n / sigma_pair_n: the independent and the shared std of log depth (module
    doc); pair_n: which pair made each (an index); rejected: candidates dropped, by reason ('behind', 'parallax',
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
    rejected = {'behind': 0, 'parallax': 0, 'reprojection': 0, 'sigma': 0, 'range': 0}
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
    rejected['behind'] = int((~front).sum())
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
    ok = front
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
    mu = float(np.median(ru))
    w = np.ones_like(ru)
    for _ in range(config.iterations):
        w = _huber_weights(ru - mu, s, config.huber_k) / s ** 2
        mu_new = float(np.sum(w * ru) / np.sum(w))
        if abs(mu_new - mu) < 1e-7:
            mu = mu_new
            break
        mu = mu_new
    w = _huber_weights(ru - mu, s, config.huber_k) / s ** 2
    inliers = int((np.abs(ru - mu) <= config.huber_k * s).sum())
    # independent part: the weighted mean's std; shared part: each pair's pose error, averaged over the pairs with
    # the share of the weight each pair has
    var_ind = 1.0 / float(np.sum(w))
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
class ScaleGrid:
    """A smooth log-scale map: node values (rows, cols) and their posterior stds, over an image of size (H, W)
    whose nodes sit at the centres of a rows x cols tiling."""
    log_scale_rc: np.ndarray
    sigma_rc: np.ndarray
    size_hw: Tuple[int, int]


def _bilinear_weights(uv_n2: np.ndarray, size_hw: Tuple[int, int], rows: int, cols: int
                      ) -> Tuple[np.ndarray, np.ndarray]:
    """(node indices (n, 4), weights (n, 4)) of the bilinear interpolation of a rows x cols node grid (nodes at the
    centres of a rows x cols tiling of the image, clamped at the borders: OpenCV's resize convention) at pixels
    uv (pixel centres at integers)."""
    H, W = size_hw
    gx = np.clip((uv_n2[:, 0] + 0.5) / W * cols - 0.5, 0, cols - 1)
    gy = np.clip((uv_n2[:, 1] + 0.5) / H * rows - 0.5, 0, rows - 1)
    x0 = np.minimum(np.floor(gx).astype(np.int64), max(cols - 2, 0))
    y0 = np.minimum(np.floor(gy).astype(np.int64), max(rows - 2, 0))
    x1, y1 = np.minimum(x0 + 1, cols - 1), np.minimum(y0 + 1, rows - 1)
    fx, fy = gx - x0, gy - y0
    idx = np.stack([y0 * cols + x0, y0 * cols + x1, y1 * cols + x0, y1 * cols + x1], 1)
    w = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], 1)
    return idx, w


def fit_scale_grid(log_ratio_n: np.ndarray, anchors: Anchors, uv_n2: np.ndarray, size_hw: Tuple[int, int],
                   fit: ScaleFit, config: AnchorConfig = AnchorConfig()) -> ScaleGrid:
    """The smooth log-scale map (module doc) at an image of ``size_hw`` from the anchors at pixels ``uv_n2`` of that
    image, their log ratios, and the global fit (its Huber weights and log scale; the map's prior)."""
    rows, cols = config.grid_rows, config.grid_cols
    n = rows * cols
    r = np.asarray(log_ratio_n, np.float64)
    use = np.isfinite(r) & (fit.weight_n > 0)
    idx, bw = _bilinear_weights(uv_n2[use], size_hw, rows, cols)
    A = np.zeros((n, n))
    rhs = np.zeros(n)
    w = fit.weight_n[use]
    # data: sum_i w_i (sum_j bw_ij g_j - r_i)^2
    for a in range(4):
        for b in range(4):
            np.add.at(A, (idx[:, a], idx[:, b]), w * bw[:, a] * bw[:, b])
        np.add.at(rhs, idx[:, a], w * bw[:, a] * r[use])
    # smoothness between 4-neighbours and the prior towards the global log scale
    ws = 1.0 / config.grid_smoothness ** 2
    for y in range(rows):
        for x in range(cols):
            i = y * cols + x
            for j in ((i + 1) if x + 1 < cols else None, (i + cols) if y + 1 < rows else None):
                if j is None:
                    continue
                A[i, i] += ws
                A[j, j] += ws
                A[i, j] -= ws
                A[j, i] -= ws
    wp = 1.0 / config.grid_prior_sigma ** 2
    A[np.diag_indices(n)] += wp
    rhs += wp * fit.log_scale
    cov = np.linalg.inv(A)
    g = cov @ rhs
    # the nodes' posterior stds, with the global fit's (its pairs' shared pose errors move every node alike)
    sigma = np.sqrt(np.maximum(np.diag(cov), 0.0) + fit.sigma ** 2)
    return ScaleGrid(g.reshape(rows, cols), sigma.reshape(rows, cols), (int(size_hw[0]), int(size_hw[1])))


def grid_log_scale_at(grid: ScaleGrid, uv_n2: np.ndarray) -> np.ndarray:
    """The map's log scale at pixels uv of its image (bilinear between nodes)."""
    rows, cols = grid.log_scale_rc.shape
    idx, w = _bilinear_weights(np.asarray(uv_n2, np.float64), grid.size_hw, rows, cols)
    return np.sum(grid.log_scale_rc.ravel()[idx] * w, axis=1)


def grid_dense(grid: ScaleGrid, values_rc: Optional[np.ndarray] = None) -> np.ndarray:
    """The map (or other node values on its grid) at every pixel of its image, (H, W): the bilinear interpolation
    of :func:`grid_log_scale_at`, as OpenCV's resize computes it."""
    H, W = grid.size_hw
    v = grid.log_scale_rc if values_rc is None else np.asarray(values_rc, np.float64)
    return cv2.resize(v.astype(np.float64), (W, H), interpolation=cv2.INTER_LINEAR)


def widened_confidence(conf: np.ndarray, sigma_log, ratio: float = 1.25) -> np.ndarray:
    """The probability of the ×ratio band once an independent log-depth error of std ``sigma_log`` (scalar or per
    pixel) is added: the confidence ``c`` read as ``P(|e| < log ratio)`` of a zero-mean Gaussian ``e``, whose
    variance is then increased by ``sigma_log^2``. A confidence of 1 stays 1 only with sigma 0; 0 stays 0."""
    c = np.clip(np.asarray(conf, np.float64), 0.0, 1.0 - 1e-9)
    band = math.log(ratio)
    with np.errstate(divide='ignore'):
        s0 = band / (math.sqrt(2.0) * np.maximum(erfinv(c), 1e-12))
    s = np.sqrt(s0 ** 2 + np.asarray(sigma_log, np.float64) ** 2)
    out = erf(band / (math.sqrt(2.0) * s))
    return np.where(c > 0, out, 0.0)
