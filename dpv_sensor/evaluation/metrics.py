"""Depth metrics (numpy): accuracy, coverage, temporal consistency and confidence quality.

All functions take z-depth images in metres (H x W float arrays). Conventions:

- **Valid GT**: finite and > 0 (0 and NaN both mean "no measurement"), optionally restricted to
  ``[min_depth, max_depth]``.
- **Prediction present**: finite and > 0 (``DepthOutput`` uses NaN, 16UC1 images use 0).
- **Evaluated pixels** = valid GT and prediction present. ``coverage`` = evaluated / valid GT.
- When ``min_depth`` / ``max_depth`` are given, predictions are clipped to that range after the
  optional median scaling (the usual Eigen/KITTI protocol); without limits nothing is clipped.
- **Median scaling** (per frame): ``pred * median(gt) / median(pred)`` over the evaluated pixels.

Error measures (``d = log pred - log gt``, means over evaluated pixels):

    abs_rel  = mean(|pred - gt| / gt)          sq_rel = mean((pred - gt)^2 / gt)
    rmse     = sqrt(mean((pred - gt)^2))       rmse_log = sqrt(mean(d^2))
    delta_k  = fraction with max(pred/gt, gt/pred) < 1.25^k, k = 1, 2, 3
    si_log   = sqrt(mean(d^2) - mean(d)^2)     (Eigen et al. 2014, scale-invariant log error)

Accumulation over frames (:class:`MetricAccumulator`) reports two averages:

- ``frame_mean`` — each frame's metric, then the mean over frames (every frame counts the same;
  the KITTI/Eigen convention). **This is the headline number of the summary.**
- ``pixel_weighted`` — all evaluated pixels of all frames pooled (frames with more valid pixels
  weigh more; rmse / rmse_log / si_log are computed from the pooled sums, so si_log there removes
  one global scale rather than one per frame).

Confidence quality: sparsification curves (remove the least confident pixels first, abs_rel of the
rest) against the oracle (remove the largest true errors first) and random removal, the area
between sparsification and oracle (AUSE, Ilg et al. 2018), and the ratio "abs_rel of the most
confident half / abs_rel of all". The per-pixel error used is the *metric* absolute relative
error (confidence is meant to predict metric error). Calibration: the published confidence is the probability
that the true depth lies within x1.25 of the published one (the delta1 event), so the expected calibration
error (ECE, 10 equal-width bins) compares each bin's mean confidence with its share of delta1 hits, and the
share of pixels kept at a ``min_confidence`` of 0.5 / 0.7 / 0.9 is reported with their delta1. The NLL of a DPV is in
:func:`dpv_sensor.core.dpv.nll`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict, Iterable, List, Optional, Tuple

import numpy as np

__all__ = [
    'ERROR_METRICS', 'DEFAULT_FRACTIONS', 'gt_valid_mask', 'pred_valid_mask', 'evaluation_mask',
    'median_scale', 'image_scale_summary', 'error_sums', 'metrics_from_sums', 'depth_metrics', 'frame_metrics',
    'temporal_consistency', 'sparsification', 'ause', 'aurg', 'confident_half_ratio', 'MetricAccumulator',
    'CALIBRATION_BINS', 'KEPT_THRESHOLDS', 'DELTA1_RATIO', 'within_ratio', 'confidence_events', 'reliability_bins',
    'expected_calibration_error', 'kept_at_thresholds', 'calibration_summary',
    'dpv_nll', 'EDGE_JUMP', 'EDGE_RADIUS', 'NORMAL_WINDOW', 'normal_window', 'PLANAR_CONSISTENCY', 'depth_edge_band',
    'depth_normals', 'planar_mask', 'edge_planarity_metrics',
]

ERROR_METRICS = ('abs_rel', 'sq_rel', 'rmse', 'rmse_log', 'delta1', 'delta2', 'delta3', 'si_log')
# Fractions of pixels removed along a sparsification curve: 0, 0.01, ..., 0.99.
DEFAULT_FRACTIONS = np.arange(100) / 100.0
# The event the published confidence is a probability of: the true depth within this factor of the published one
# (the delta1 band).
DELTA1_RATIO = 1.25
# Equal-width confidence bins of the reliability diagram and the ECE.
CALIBRATION_BINS = 10
# Confidence thresholds (min_confidence operating points) at which the share kept and its delta1 are reported.
KEPT_THRESHOLDS = (0.5, 0.7, 0.9)


# ----------------------------------------------------------------------------------------------
# Masks and scaling
# ----------------------------------------------------------------------------------------------

def gt_valid_mask(gt: np.ndarray, min_depth: Optional[float] = None,
                  max_depth: Optional[float] = None) -> np.ndarray:
    """True where the GT depth is finite, > 0 and inside the optional [min_depth, max_depth]."""
    gt = np.asarray(gt)
    with np.errstate(invalid='ignore'):
        m = np.isfinite(gt) & (gt > 0)
        if min_depth is not None:
            m &= gt >= min_depth
        if max_depth is not None:
            m &= gt <= max_depth
    return m


def pred_valid_mask(pred: np.ndarray) -> np.ndarray:
    """True where there is a prediction: finite and > 0."""
    pred = np.asarray(pred)
    with np.errstate(invalid='ignore'):
        return np.isfinite(pred) & (pred > 0)


def evaluation_mask(pred: np.ndarray, gt: np.ndarray, min_depth: Optional[float] = None,
                    max_depth: Optional[float] = None, mask: Optional[np.ndarray] = None) -> np.ndarray:
    """Pixels that are scored: valid GT, a prediction present, and the optional extra ``mask``."""
    pred, gt = np.asarray(pred), np.asarray(gt)
    if pred.shape != gt.shape:
        raise ValueError(f'prediction shape {pred.shape} differs from GT shape {gt.shape}')
    m = gt_valid_mask(gt, min_depth, max_depth) & pred_valid_mask(pred)
    if mask is not None:
        m &= np.asarray(mask, dtype=bool)
    return m


def median_scale(pred_n: np.ndarray, gt_n: np.ndarray) -> float:
    """The per-frame median-scaling factor ``median(gt) / median(pred)`` (1.0 when empty)."""
    if pred_n.size == 0:
        return 1.0
    return float(np.median(gt_n) / np.median(pred_n))


def image_scale_summary(pairs, min_depth: Optional[float] = None, max_depth: Optional[float] = None
                        ) -> Dict[str, Optional[float]]:
    """How the depth's scale wanders from image to image: for each (prediction, GT) pair its scale, the median of
    prediction / GT over the scored pixels; then their quartiles ('q25', 'median', 'q75') and 'iqr' over the images,
    and 'scaled_abs_rel': the frame mean of abs_rel once each image is divided by its own scale (what a perfect
    per-image scale correction would leave). None with no scored image."""
    scales, scaled = [], []
    for pred, gt in pairs:
        m = evaluation_mask(pred, gt, min_depth, max_depth)
        if not m.any():
            continue
        p, g = np.asarray(pred, np.float64)[m], np.asarray(gt, np.float64)[m]
        s = float(np.median(p / g))
        scales.append(s)
        scaled.append(float(np.mean(np.abs(p / s - g) / g)))
    if not scales:
        return {'q25': None, 'median': None, 'q75': None, 'iqr': None, 'scaled_abs_rel': None, 'images': 0}
    q25, q50, q75 = (float(v) for v in np.percentile(scales, [25, 50, 75]))
    return {'q25': q25, 'median': q50, 'q75': q75, 'iqr': q75 - q25, 'scaled_abs_rel': float(np.mean(scaled)),
            'images': len(scales)}


def _clip(pred_n: np.ndarray, min_depth, max_depth) -> np.ndarray:
    if min_depth is None and max_depth is None:
        return pred_n
    return np.clip(pred_n, min_depth if min_depth is not None else 0.0,
                   max_depth if max_depth is not None else np.inf)


# ----------------------------------------------------------------------------------------------
# Error sums (so frames can be pooled) and the metrics derived from them
# ----------------------------------------------------------------------------------------------

_SUM_KEYS = ('n', 'abs_rel', 'sq_rel', 'sq', 'log_sq', 'log', 'delta1', 'delta2', 'delta3')


def error_sums(pred_n: np.ndarray, gt_n: np.ndarray) -> Dict[str, float]:
    """Sufficient statistics of the error measures over 1-D arrays of evaluated pixels.

    Keys: n, abs_rel (sum |e|/gt), sq_rel (sum e^2/gt), sq (sum e^2), log_sq (sum d^2), log (sum d),
    delta1..3 (counts). Computed in float64.
    """
    p = np.asarray(pred_n, dtype=np.float64).ravel()
    g = np.asarray(gt_n, dtype=np.float64).ravel()
    e = p - g
    d = np.log(p) - np.log(g)
    ratio = np.maximum(p / g, g / p)
    return {
        'n': float(p.size),
        'abs_rel': float(np.sum(np.abs(e) / g)),
        'sq_rel': float(np.sum(e * e / g)),
        'sq': float(np.sum(e * e)),
        'log_sq': float(np.sum(d * d)),
        'log': float(np.sum(d)),
        'delta1': float(np.sum(ratio < 1.25)),
        'delta2': float(np.sum(ratio < 1.25 ** 2)),
        'delta3': float(np.sum(ratio < 1.25 ** 3)),
    }


def metrics_from_sums(s: Dict[str, float]) -> Dict[str, float]:
    """abs_rel, sq_rel, rmse, rmse_log, delta1..3, si_log from :func:`error_sums` (NaN if n = 0)."""
    n = s['n']
    if n <= 0:
        return {k: float('nan') for k in ERROR_METRICS}
    mean_d2 = s['log_sq'] / n
    mean_d = s['log'] / n
    return {
        'abs_rel': s['abs_rel'] / n,
        'sq_rel': s['sq_rel'] / n,
        'rmse': math.sqrt(s['sq'] / n),
        'rmse_log': math.sqrt(mean_d2),
        'delta1': s['delta1'] / n,
        'delta2': s['delta2'] / n,
        'delta3': s['delta3'] / n,
        # max(0, .) guards the rounding of a perfectly scaled prediction (variance ~ -1e-17).
        'si_log': math.sqrt(max(mean_d2 - mean_d * mean_d, 0.0)),
    }


def depth_metrics(pred: np.ndarray, gt: np.ndarray, *, median_scaling: bool = False,
                  min_depth: Optional[float] = None, max_depth: Optional[float] = None,
                  mask: Optional[np.ndarray] = None) -> Dict[str, float]:
    """The error measures of one frame (see the module docstring), plus ``coverage``, ``num_pixels``
    and ``scale`` (the median-scaling factor applied, 1.0 for metric).

    Metrics are NaN when no pixel is evaluated.
    """
    m = evaluation_mask(pred, gt, min_depth, max_depth, mask)
    gvalid = gt_valid_mask(gt, min_depth, max_depth)
    if mask is not None:
        gvalid &= np.asarray(mask, dtype=bool)
    n_gt = int(gvalid.sum())
    p = np.asarray(pred, dtype=np.float64)[m]
    g = np.asarray(gt, dtype=np.float64)[m]
    scale = median_scale(p, g) if median_scaling else 1.0
    p = _clip(p * scale, min_depth, max_depth)
    out = metrics_from_sums(error_sums(p, g))
    out['coverage'] = (m.sum() / n_gt) if n_gt > 0 else float('nan')
    out['num_pixels'] = int(m.sum())
    out['scale'] = scale
    return out


def frame_metrics(pred: np.ndarray, gt: np.ndarray, *, min_depth: Optional[float] = None,
                  max_depth: Optional[float] = None) -> Dict[str, Dict[str, float]]:
    """``{'metric': depth_metrics(...), 'median_scaled': depth_metrics(..., median_scaling=True)}``."""
    return {'metric': depth_metrics(pred, gt, min_depth=min_depth, max_depth=max_depth),
            'median_scaled': depth_metrics(pred, gt, median_scaling=True, min_depth=min_depth,
                                           max_depth=max_depth)}


# ----------------------------------------------------------------------------------------------
# Depth edges and planar surfaces
# ----------------------------------------------------------------------------------------------
#
# Two views of the *shape* of a depth image that the pixel averages above hide. Edges: abs_rel in the
# band within ``radius`` pixels (Chebyshev distance) of a GT depth jump (two 4-neighbours whose GT depths
# differ by more than ``jump``, relative to the nearer) against abs_rel elsewhere: blurred or misplaced
# object boundaries raise the first. Planarity: the angle between surface normals of prediction and GT on
# GT planar regions: terraces (steps between depth planes) and bumps raise it while barely moving abs_rel.
# Normals are the smallest principal axis of the back-projected points in a ``window`` x ``window``
# neighbourhood (a local plane fit, robust to sensor noise and quantisation), oriented towards the camera.
# The default window grows with the image (:func:`normal_window`: width / 16, odd, at least 7; 41 px at
# 640 wide, about 15 cm at 2 m): a 7 px fit on a 640 px image spans 3 cm at 2 m, less than the depth
# noise of any sensor here, and its normals would score noise rather than shape.
# A pixel is planar when its whole GT window is valid, it is outside the edge band, and the GT normals of
# its window agree: the length of their mean is at least ``planar_consistency`` (0.995: a mean angular
# spread of about 6 degrees).

EDGE_JUMP = 0.10
EDGE_RADIUS = 3
NORMAL_WINDOW = 7          # the smallest window (and the one of images up to 127 px wide)


def normal_window(width: int) -> int:
    """The default normal window of an image ``width`` pixels wide: width / 16, made odd, at least 7."""
    return max(NORMAL_WINDOW, (int(width) // 16) | 1)
PLANAR_CONSISTENCY = 0.995


def depth_edge_band(gt: np.ndarray, jump: float = EDGE_JUMP, radius: int = EDGE_RADIUS) -> np.ndarray:
    """(H, W) bool: pixels within ``radius`` px (Chebyshev) of a GT depth jump larger than ``jump``.

    A jump is a pair of 4-neighbours, both with valid GT, whose depths differ by more than ``jump`` times
    the nearer one; both pixels of the pair are edge pixels. Invalid GT never makes an edge."""
    from scipy.ndimage import binary_dilation
    g = np.asarray(gt, np.float64)
    valid = gt_valid_mask(g)
    gz = np.where(valid, g, 1.0)
    edge = np.zeros(g.shape, bool)
    for a, b, va, vb in ((gz[:, :-1], gz[:, 1:], valid[:, :-1], valid[:, 1:]),
                         (gz[:-1, :], gz[1:, :], valid[:-1, :], valid[1:, :])):
        j = va & vb & (np.maximum(a, b) > (1.0 + jump) * np.minimum(a, b))
        if a.shape[1] != g.shape[1]:
            edge[:, :-1] |= j
            edge[:, 1:] |= j
        else:
            edge[:-1, :] |= j
            edge[1:, :] |= j
    if radius > 0 and edge.any():
        edge = binary_dilation(edge, structure=np.ones((2 * radius + 1, 2 * radius + 1), bool))
    return edge


def depth_normals(depth: np.ndarray, K: np.ndarray, window: Optional[int] = None) -> Tuple[np.ndarray, np.ndarray]:
    """Surface normals of a z-depth image: ((H, W, 3) unit normals facing the camera, (H, W) bool valid).

    Each normal is the smallest principal axis of the back-projected points (intrinsics ``K``) of the
    ``window`` x ``window`` neighbourhood (default :func:`normal_window`); valid where that whole
    neighbourhood has depth (finite, > 0)."""
    from scipy.ndimage import uniform_filter
    z = np.asarray(depth, np.float64)
    H, W = z.shape
    window = normal_window(W) if window is None else int(window)
    K = np.asarray(K, np.float64)
    valid = pred_valid_mask(z)
    z0 = np.where(valid, z, 0.0)
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    X = (u - K[0, 2]) / K[0, 0] * z0
    Y = (v - K[1, 2]) / K[1, 1] * z0
    P = (X, Y, z0)

    def box(a):
        return uniform_filter(a, size=window, mode='constant', cval=0.0)

    full = box(valid.astype(np.float64)) > 1.0 - 1e-9
    normals = np.zeros((H, W, 3), np.float64)
    if not full.any():
        return normals, full
    mu = [box(p)[full] for p in P]
    C = np.empty((int(full.sum()), 3, 3), np.float64)
    for i in range(3):
        for j in range(i, 3):
            C[:, i, j] = C[:, j, i] = box(P[i] * P[j])[full] - mu[i] * mu[j]
    _w, vecs = np.linalg.eigh(C)
    n = vecs[:, :, 0]                                         # eigenvalues ascending: smallest axis
    centre = np.stack(mu, 1)
    n = np.where((np.sum(n * centre, 1) > 0)[:, None], -n, n)  # face the camera
    normals[full] = n / np.linalg.norm(n, axis=1, keepdims=True)
    return normals, full


def planar_mask(gt: np.ndarray, K: np.ndarray, window: Optional[int] = None,
                consistency: float = PLANAR_CONSISTENCY, edge_band: Optional[np.ndarray] = None,
                normals: Optional[Tuple[np.ndarray, np.ndarray]] = None) -> np.ndarray:
    """(H, W) bool: GT planar pixels (see the section comment): GT normal valid, outside ``edge_band``
    (default :func:`depth_edge_band` of ``gt``), and the GT normals of the window agree."""
    from scipy.ndimage import uniform_filter
    window = normal_window(np.shape(gt)[1]) if window is None else int(window)
    n, ok = normals if normals is not None else depth_normals(gt, K, window)
    band = depth_edge_band(gt) if edge_band is None else edge_band
    okf = ok.astype(np.float64)
    full = uniform_filter(okf, size=window, mode='constant') > 1.0 - 1e-9
    mean = np.stack([uniform_filter(n[..., i] * okf, size=window, mode='constant') for i in range(3)], -1)
    return ok & full & ~band & (np.linalg.norm(mean, axis=-1) >= consistency)


def edge_planarity_metrics(pred: np.ndarray, gt: np.ndarray, K: Optional[np.ndarray] = None, *,
                           min_depth: Optional[float] = None, max_depth: Optional[float] = None,
                           jump: float = EDGE_JUMP, radius: int = EDGE_RADIUS,
                           window: Optional[int] = None) -> Dict[str, float]:
    """Edge and planarity measures of one frame (metric depth, clipped like the other measures).

    ``edge_abs_rel`` / ``nonedge_abs_rel``: abs_rel over evaluated pixels inside / outside the GT edge band
    (:func:`depth_edge_band`); ``edge_pixels``. With ``K``: ``normal_err_deg`` (mean angle between the
    predicted and GT normals over the GT planar pixels where the prediction has a normal) and
    ``planar_pixels`` (how many such pixels). NaN where no pixel qualifies."""
    pred = np.asarray(pred, np.float64)
    gt = np.asarray(gt, np.float64)
    m = evaluation_mask(pred, gt, min_depth, max_depth)
    band = depth_edge_band(gt, jump, radius)
    out: Dict[str, float] = {}
    for key, sel in (('edge', m & band), ('nonedge', m & ~band)):
        p = _clip(pred[sel], min_depth, max_depth)
        g = gt[sel]
        out[f'{key}_abs_rel'] = float(np.mean(np.abs(p - g) / g)) if g.size else float('nan')
    out['edge_pixels'] = int((m & band).sum())
    if K is not None:
        g_in = np.where(gt_valid_mask(gt, min_depth, max_depth), gt, np.nan)
        gn = depth_normals(g_in, K, window)
        planar = planar_mask(g_in, K, window, edge_band=band, normals=gn)
        pn, pok = depth_normals(pred, K, window)
        sel = planar & pok
        cos = np.clip(np.sum(pn[sel] * gn[0][sel], axis=1), -1.0, 1.0)
        out['normal_err_deg'] = float(np.degrees(np.arccos(cos)).mean()) if cos.size else float('nan')
        out['planar_pixels'] = int(sel.sum())
    return out


# ----------------------------------------------------------------------------------------------
# Temporal consistency
# ----------------------------------------------------------------------------------------------

def _bilinear_valid(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Bilinear samples of ``img`` at (u, v); valid only where all four neighbours are > 0 and finite
    (no blending across holes). Coordinates must lie inside [0, W-1] x [0, H-1]."""
    H, W = img.shape
    u0 = np.clip(np.floor(u).astype(np.int64), 0, max(W - 2, 0))
    v0 = np.clip(np.floor(v).astype(np.int64), 0, max(H - 2, 0))
    u1 = np.minimum(u0 + 1, W - 1)
    v1 = np.minimum(v0 + 1, H - 1)
    a, b = u - u0, v - v0
    q = [img[v0, u0], img[v0, u1], img[v1, u0], img[v1, u1]]
    w = [(1 - a) * (1 - b), a * (1 - b), (1 - a) * b, a * b]
    ok = np.ones(u.shape, bool)
    val = np.zeros(u.shape, np.float64)
    for qi, wi in zip(q, w):
        good = np.isfinite(qi) & (qi > 0)
        # A neighbour with zero weight may be a hole without spoiling the sample.
        ok &= good | (wi <= 1e-9)
        val += np.where(good, qi, 0.0) * wi
    return val, ok


def reproject(depth_hw: np.ndarray, K_a: np.ndarray, K_b: np.ndarray, T_b_a: np.ndarray,
              size_b_hw: Tuple[int, int]) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Move every pixel of camera a, at ``depth_hw`` (metres; use 0 where there is none), into camera b.

    Returns flat arrays over a's pixels (row-major): b's pixel coordinates u, v, the depth z in b, and whether
    the point lies in front of b (z > 1e-6) and inside its ``(H, W)`` image (``0..W-1`` x ``0..H-1``)."""
    H, W = np.shape(depth_hw)
    Hb, Wb = size_b_hw
    T_b_a = np.asarray(T_b_a, np.float64)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    rays = np.linalg.inv(np.asarray(K_a, np.float64)) @ np.stack([u.ravel(), v.ravel(), np.ones(H * W)])
    X = rays * np.asarray(depth_hw, np.float64).ravel()[None]
    Xb = T_b_a[:3, :3] @ X + T_b_a[:3, 3:4]
    z = Xb[2]
    zs = np.where(z > 1e-6, z, 1.0)
    p = np.asarray(K_b, np.float64) @ Xb
    ub, vb = p[0] / zs, p[1] / zs
    inside = (z > 1e-6) & (ub >= 0) & (ub <= Wb - 1) & (vb >= 0) & (vb <= Hb - 1)
    return ub, vb, z, inside


def temporal_consistency(depth_a: np.ndarray, depth_b: np.ndarray, K_a: np.ndarray, K_b: np.ndarray,
                         T_world_a: np.ndarray, T_world_b: np.ndarray, *,
                         gt_a: Optional[np.ndarray] = None, gt_b: Optional[np.ndarray] = None,
                         occlusion_tol: float = 0.05) -> Tuple[float, int]:
    """Mean absolute relative disagreement of two consecutive depth maps, and the pixel count.

    Every pixel of ``depth_a`` with a prediction is back-projected with ``K_a``, moved into camera b
    with ``T_b_a = inv(T_world_b) T_world_a``, and projected with ``K_b``; where it lands inside
    image b in front of the camera and ``depth_b`` has a prediction there (bilinear, all four
    neighbours present), the error is ``|depth_b(u', v') - z_b| / z_b`` with ``z_b`` the transformed
    z. Returns (mean error, number of pixels); (NaN, 0) when no pixel is visible in both.

    Visibility: with ``gt_a`` and ``gt_b`` given, only pixels that are truly visible in both frames
    count: GT-valid in a, and the GT of b at the re-projection (of the GT point) agrees with the
    transformed GT z within ``occlusion_tol`` (relative). Without GT, every re-projected pixel counts
    (occlusions then show up as inconsistency).
    """
    da = np.asarray(depth_a, np.float64)
    db = np.asarray(depth_b, np.float64)
    H, W = da.shape
    Hb, Wb = db.shape
    T_b_a = np.linalg.inv(np.asarray(T_world_b, np.float64)) @ np.asarray(T_world_a, np.float64)

    def move(depth_flat):
        return reproject(depth_flat.reshape(H, W), K_a, K_b, T_b_a, (Hb, Wb))

    flat = da.ravel()
    have = pred_valid_mask(flat)
    ub, vb, z, inside = move(np.where(have, flat, 0.0))
    sel = have & inside
    if gt_a is not None and gt_b is not None:
        ga = np.asarray(gt_a, np.float64).ravel()
        gvalid = gt_valid_mask(ga)
        gu, gv, gz, ginside = move(np.where(gvalid, ga, 0.0))
        vis = gvalid & ginside
        idx = np.flatnonzero(vis)
        gb_s, gb_ok = _bilinear_valid(np.asarray(gt_b, np.float64), gu[idx], gv[idx])
        agree = gb_ok & (np.abs(gb_s - gz[idx]) <= occlusion_tol * gz[idx])
        visible = np.zeros(H * W, bool)
        visible[idx[agree]] = True
        sel &= visible
    idx = np.flatnonzero(sel)
    if idx.size == 0:
        return float('nan'), 0
    sampled, ok = _bilinear_valid(db, ub[idx], vb[idx])
    if not ok.any():
        return float('nan'), 0
    err = np.abs(sampled[ok] - z[idx][ok]) / z[idx][ok]
    return float(err.mean()), int(ok.sum())


# ----------------------------------------------------------------------------------------------
# Confidence quality
# ----------------------------------------------------------------------------------------------

def _removal_curve(err_n: np.ndarray, order_n: np.ndarray, fractions: np.ndarray) -> np.ndarray:
    """Mean of ``err_n`` over the pixels kept after removing the first ``floor(f * N)`` of ``order_n``."""
    N = err_n.size
    e = err_n[order_n]
    # suffix[k] = sum of e[k:]
    suffix = np.concatenate([np.cumsum(e[::-1])[::-1], [0.0]])
    k = np.minimum(np.floor(np.asarray(fractions) * N + 1e-9).astype(np.int64), N - 1)
    return suffix[k] / (N - k)


def sparsification(err_n: np.ndarray, conf_n: np.ndarray,
                   fractions: np.ndarray = DEFAULT_FRACTIONS) -> Dict[str, np.ndarray]:
    """Sparsification curves of one set of pixels.

    err_n: per-pixel error (e.g. metric |pred - gt| / gt), conf_n: confidence (higher = more certain).
    For each fraction f of pixels removed, the mean error of the rest when removing:
    ``sparsification`` — the least confident first; ``oracle`` — the largest errors first;
    ``random`` — at random (its expectation: the mean error of all pixels, a flat line).
    Ties in confidence are broken by pixel order (stable sort). Returns dict of arrays with
    ``fractions``; all NaN when there are no pixels.
    """
    err = np.asarray(err_n, np.float64).ravel()
    conf = np.asarray(conf_n, np.float64).ravel()
    fr = np.asarray(fractions, np.float64)
    if err.size == 0:
        nan = np.full(fr.shape, np.nan)
        return {'fractions': fr, 'sparsification': nan, 'oracle': nan.copy(), 'random': nan.copy()}
    by_conf = np.argsort(conf, kind='stable')           # lowest confidence first
    by_err = np.argsort(-err, kind='stable')            # largest error first
    return {'fractions': fr,
            'sparsification': _removal_curve(err, by_conf, fr),
            'oracle': _removal_curve(err, by_err, fr),
            'random': np.full(fr.shape, err.mean())}


def ause(curves: Dict[str, np.ndarray]) -> float:
    """Area Under the Sparsification Error: trapezoid integral over the fractions of
    (sparsification - oracle). 0 when confidence orders the errors perfectly; larger is worse."""
    f = curves['fractions']
    diff = curves['sparsification'] - curves['oracle']
    return float(np.sum(0.5 * (diff[1:] + diff[:-1]) * np.diff(f)))


def aurg(curves: Dict[str, np.ndarray]) -> float:
    """Area between the random curve and the sparsification curve (positive = better than random)."""
    f = curves['fractions']
    diff = curves['random'] - curves['sparsification']
    return float(np.sum(0.5 * (diff[1:] + diff[:-1]) * np.diff(f)))


def confident_half_ratio(err_n: np.ndarray, conf_n: np.ndarray) -> float:
    """abs_rel (mean error) of the most confident half of the pixels divided by that of all pixels.

    Below 1 means the confidence singles out the better half. NaN when empty or the error is 0.
    """
    err = np.asarray(err_n, np.float64).ravel()
    conf = np.asarray(conf_n, np.float64).ravel()
    if err.size == 0 or err.mean() == 0:
        return float('nan')
    order = np.argsort(conf, kind='stable')
    keep = order[err.size // 2:]
    return float(err[keep].mean() / err.mean())


def within_ratio(pred_n: np.ndarray, gt_n: np.ndarray, ratio: float = DELTA1_RATIO) -> np.ndarray:
    """bool per pixel: ``max(pred / gt, gt / pred) < ratio`` (the delta1 event for ratio 1.25)."""
    p = np.asarray(pred_n, np.float64)
    g = np.asarray(gt_n, np.float64)
    return np.maximum(p / g, g / p) < ratio


def confidence_events(pred: np.ndarray, gt: np.ndarray, conf: np.ndarray, min_depth: Optional[float] = None,
                      max_depth: Optional[float] = None) -> Tuple[np.ndarray, np.ndarray]:
    """(confidence, hit) of the evaluated pixels of one frame (:func:`evaluation_mask`), the pairs calibration is
    measured and fitted on: the confidence (NaN read as 0) and whether the true depth lies within x1.25 of the
    prediction (clipped to [min_depth, max_depth] as scored, :func:`within_ratio`). 1-D float64 and bool."""
    conf = np.asarray(conf, np.float64)
    if conf.shape != np.shape(gt):
        raise ValueError(f'confidence shape {conf.shape} differs from GT shape {np.shape(gt)}')
    m = evaluation_mask(pred, gt, min_depth, max_depth)
    p = _clip(np.asarray(pred, np.float64)[m], min_depth, max_depth)
    return np.nan_to_num(conf[m], nan=0.0), within_ratio(p, np.asarray(gt, np.float64)[m])


def reliability_bins(conf_n: np.ndarray, hit_n: np.ndarray, bins: int = CALIBRATION_BINS) -> Dict[str, np.ndarray]:
    """Reliability diagram data: ``bins`` equal-width confidence bins on [0, 1] (the last one closed); per bin
    the pixel count, the mean confidence and the share of pixels whose event happened (``hit_n``).
    Empty bins have NaN means."""
    c = np.clip(np.asarray(conf_n, np.float64).ravel(), 0.0, 1.0)
    h = np.asarray(hit_n, np.float64).ravel()
    idx = np.minimum((c * bins).astype(np.int64), bins - 1)
    count = np.bincount(idx, minlength=bins).astype(np.float64)
    with np.errstate(invalid='ignore', divide='ignore'):
        mean_conf = np.bincount(idx, weights=c, minlength=bins) / count
        hit_rate = np.bincount(idx, weights=h, minlength=bins) / count
    return {'edges': np.linspace(0.0, 1.0, bins + 1), 'count': count, 'mean_confidence': mean_conf,
            'hit_rate': hit_rate}


def expected_calibration_error(conf_n: np.ndarray, hit_n: np.ndarray, bins: int = CALIBRATION_BINS) -> float:
    """ECE: sum over equal-width confidence bins of (share of pixels in the bin) x |mean confidence - share of
    hits| (Guo et al. 2017). 0 = calibrated; NaN without pixels."""
    r = reliability_bins(conf_n, hit_n, bins)
    n = r['count'].sum()
    if n == 0:
        return float('nan')
    used = r['count'] > 0
    return float(np.sum(r['count'][used] / n * np.abs(r['mean_confidence'][used] - r['hit_rate'][used])))


def kept_at_thresholds(conf_n: np.ndarray, hit_n: np.ndarray,
                       thresholds: Iterable[float] = KEPT_THRESHOLDS) -> Dict[str, Dict[str, float]]:
    """Per ``min_confidence`` threshold t: ``share`` of the pixels with confidence >= t and ``delta1`` (share of
    hits) among them (NaN when none is kept). Keys are formatted like '0.9'."""
    c = np.asarray(conf_n, np.float64).ravel()
    h = np.asarray(hit_n, bool).ravel()
    out = {}
    for t in thresholds:
        keep = c >= float(t)
        out[f'{float(t):g}'] = {'share': float(keep.mean()) if c.size else float('nan'),
                                'delta1': float(h[keep].mean()) if keep.any() else float('nan')}
    return out


def calibration_summary(conf_n: np.ndarray, hit_n: np.ndarray, bins: int = CALIBRATION_BINS,
                        thresholds: Iterable[float] = KEPT_THRESHOLDS) -> Dict:
    """How far the confidence is a probability of the delta1 event: ``ece``, ``mean_confidence`` vs ``hit_rate``
    (the delta1 of all pixels), ``kept`` (:func:`kept_at_thresholds`) and the reliability ``bins``."""
    c = np.asarray(conf_n, np.float64).ravel()
    h = np.asarray(hit_n, bool).ravel()
    r = reliability_bins(c, h, bins)
    return {'ece': expected_calibration_error(c, h, bins),
            'mean_confidence': float(c.mean()) if c.size else float('nan'),
            'hit_rate': float(h.mean()) if h.size else float('nan'),
            'num_pixels': int(c.size),
            'kept': kept_at_thresholds(c, h, thresholds),
            'bins': {k: v.tolist() for k, v in r.items()}}


def dpv_nll(logp_bdhw, depths_d, gt_bhw, mask_bhw=None) -> float:
    """Mean NLL of the GT depth under a DPV (numpy or torch inputs): :func:`dpv_sensor.core.dpv.nll` with
    ``reduction='mean'`` (GT outside the planes' range and masked pixels excluded), as a float."""
    import torch
    from dpv_sensor.core.dpv import nll
    logp = torch.as_tensor(logp_bdhw)
    gt = torch.as_tensor(gt_bhw, dtype=logp.dtype)
    mask = None if mask_bhw is None else torch.as_tensor(mask_bhw, dtype=torch.bool)
    return float(nll(logp, torch.as_tensor(depths_d, dtype=logp.dtype), gt, mask, reduction='mean'))


# ----------------------------------------------------------------------------------------------
# Accumulation over frames
# ----------------------------------------------------------------------------------------------

def _nanmean(values: Iterable[float]) -> float:
    arr = np.asarray([v for v in values if v is not None], np.float64)
    arr = arr[np.isfinite(arr)]
    return float(arr.mean()) if arr.size else float('nan')


@dataclass
class MetricAccumulator:
    """Collects per-frame metrics and pools them.

    ``add(pred, gt, confidence=None, ...)`` scores one frame (metric and median-scaled), keeps the
    per-frame row and the pooled sums, and, with a confidence map, the frame's sparsification curves.
    ``add_temporal(value, n)`` records one temporal-consistency pair. ``summary()`` returns
    ``frame_mean`` (headline: mean over frames) and ``pixel_weighted`` (pooled pixels) for both
    ``metric`` and ``median_scaled``, plus coverage, confidence quality and temporal consistency, and the
    ``constant`` baseline (abs_rel and delta1 of every scored pixel at the frame's median GT depth, on the
    same pixels: what a depth must beat to say more than "the scene is about this far").

    The confidence quality is given per frame (``confident_half_ratio_frame_mean``: does the confidence find the
    better half *within* each image) and pooled (``confident_half_ratio_pooled``: the most confident half of all
    scored pixels of all frames, as a user thresholding the confidence over a whole run sees it; it also ranks
    whole frames against each other). The pooled figure keeps every ``pool_stride``-th scored pixel of each
    frame (deterministic, in proportion to each frame's pixels).
    """
    min_depth: Optional[float] = None
    max_depth: Optional[float] = None
    fractions: np.ndarray = field(default_factory=lambda: DEFAULT_FRACTIONS.copy())
    rows: List[Dict] = field(default_factory=list)
    _sums: Dict[str, Dict[str, float]] = field(default_factory=lambda: {
        'metric': {k: 0.0 for k in _SUM_KEYS}, 'median_scaled': {k: 0.0 for k in _SUM_KEYS}})
    _n_gt: int = 0
    _n_eval: int = 0
    _curves: List[Dict[str, np.ndarray]] = field(default_factory=list)
    _temporal: List[Tuple[float, int]] = field(default_factory=list)
    pool_stride: int = 8
    _pooled: List[Tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    _pooled_hit: List[np.ndarray] = field(default_factory=list)

    def add(self, pred: np.ndarray, gt: np.ndarray, confidence: Optional[np.ndarray] = None,
            K: Optional[np.ndarray] = None, **extra) -> Dict:
        """Score one frame; ``extra`` (e.g. index=, stamp=) is copied into its row. Returns the row:
        flat keys ``<metric>`` (metric), ``ms_<metric>`` (median-scaled), coverage, num_pixels,
        scale, the edge measures of :func:`edge_planarity_metrics` (``edge_abs_rel``, ``nonedge_abs_rel``,
        ``edge_pixels``; with the intrinsics ``K`` of the images also ``normal_err_deg``, ``planar_pixels``),
        and with confidence ``ause``, ``confident_half_ratio``, ``mean_confidence``."""
        gvalid = gt_valid_mask(gt, self.min_depth, self.max_depth)
        m = evaluation_mask(pred, gt, self.min_depth, self.max_depth)
        p = np.asarray(pred, np.float64)[m]
        g = np.asarray(gt, np.float64)[m]
        row: Dict = dict(extra)
        for kind in ('metric', 'median_scaled'):
            scale = median_scale(p, g) if kind == 'median_scaled' else 1.0
            ps = _clip(p * scale, self.min_depth, self.max_depth)
            sums = error_sums(ps, g)
            for k in _SUM_KEYS:
                self._sums[kind][k] += sums[k]
            vals = metrics_from_sums(sums)
            prefix = '' if kind == 'metric' else 'ms_'
            row.update({prefix + k: v for k, v in vals.items()})
            if kind == 'median_scaled':
                row['scale'] = scale
        # the constant baseline on the same pixels: every pixel at the median GT depth of the scored pixels
        # (an oracle constant: it knows the frame's median depth)
        if g.size:
            const = metrics_from_sums(error_sums(np.full_like(g, np.median(g)), g))
            row['const_abs_rel'], row['const_delta1'] = const['abs_rel'], const['delta1']
        else:
            row['const_abs_rel'] = row['const_delta1'] = float('nan')
        n_gt = int(gvalid.sum())
        self._n_gt += n_gt
        self._n_eval += int(m.sum())
        row['coverage'] = (m.sum() / n_gt) if n_gt else float('nan')
        row['num_pixels'] = int(m.sum())
        row.update(edge_planarity_metrics(pred, gt, K, min_depth=self.min_depth, max_depth=self.max_depth))
        if confidence is not None:
            c, hit = confidence_events(pred, gt, confidence, self.min_depth, self.max_depth)
            pc = _clip(p, self.min_depth, self.max_depth)
            err = np.abs(pc - g) / g
            row['mean_confidence'] = float(c.mean()) if c.size else float('nan')
            if err.size:
                curves = sparsification(err, c, self.fractions)
                self._curves.append(curves)
                row['ause'] = ause(curves)
                row['confident_half_ratio'] = confident_half_ratio(err, c)
                self._pooled.append((err[::self.pool_stride].astype(np.float32),
                                     c[::self.pool_stride].astype(np.float32)))
                self._pooled_hit.append(hit[::self.pool_stride])
            else:
                row['ause'] = float('nan')
                row['confident_half_ratio'] = float('nan')
        self.rows.append(row)
        return row

    def _edge_summary(self) -> Dict[str, float]:
        """Edge-band / elsewhere abs_rel and planar normal error: frame means, and pixel-weighted means
        (each frame's value weighted by its edge / planar pixel count)."""
        def weighted(key, count):
            pairs = [(r.get(key), r.get(count, 0)) for r in self.rows]
            pairs = [(v, n) for v, n in pairs if v is not None and np.isfinite(v) and n > 0]
            tot = sum(n for _, n in pairs)
            return sum(v * n for v, n in pairs) / tot if tot else float('nan')
        return {'edge_abs_rel_frame_mean': _nanmean(r.get('edge_abs_rel') for r in self.rows),
                'nonedge_abs_rel_frame_mean': _nanmean(r.get('nonedge_abs_rel') for r in self.rows),
                'normal_err_deg_frame_mean': _nanmean(r.get('normal_err_deg') for r in self.rows),
                'edge_abs_rel_pixel_weighted': weighted('edge_abs_rel', 'edge_pixels'),
                'normal_err_deg_pixel_weighted': weighted('normal_err_deg', 'planar_pixels'),
                'jump': EDGE_JUMP, 'radius_px': EDGE_RADIUS, 'normal_window': 'image width / 16, odd, >= 7 px'}

    def add_temporal(self, value: float, num_pixels: int) -> None:
        """Record the temporal consistency of one pair of consecutive keyframes."""
        self._temporal.append((float(value), int(num_pixels)))

    def pooled_confident_half_ratio(self) -> float:
        """:func:`confident_half_ratio` over the kept pixels of all frames together (NaN without any)."""
        if not self._pooled:
            return float('nan')
        return confident_half_ratio(np.concatenate([e for e, _ in self._pooled]),
                                    np.concatenate([c for _, c in self._pooled]))

    def mean_curves(self) -> Optional[Dict[str, np.ndarray]]:
        """Sparsification / oracle / random curves averaged over frames (None without confidence)."""
        if not self._curves:
            return None
        out = {'fractions': self.fractions.copy()}
        for key in ('sparsification', 'oracle', 'random'):
            out[key] = np.nanmean(np.stack([c[key] for c in self._curves]), axis=0)
        return out

    def summary(self) -> Dict:
        """A JSON-ready dict (floats; NaN where undefined). See the class docstring."""
        out: Dict = {'num_frames': len(self.rows),
                     'num_scored_frames': sum(1 for r in self.rows if r.get('num_pixels', 0) > 0),
                     'headline': 'frame_mean',
                     'min_depth': self.min_depth, 'max_depth': self.max_depth}
        for kind, prefix in (('metric', ''), ('median_scaled', 'ms_')):
            out[kind] = {
                'frame_mean': {k: _nanmean(r.get(prefix + k) for r in self.rows) for k in ERROR_METRICS},
                'pixel_weighted': metrics_from_sums(self._sums[kind]),
            }
        out['constant'] = {'frame_mean': {'abs_rel': _nanmean(r.get('const_abs_rel') for r in self.rows),
                                          'delta1': _nanmean(r.get('const_delta1') for r in self.rows)}}
        out['coverage'] = {'frame_mean': _nanmean(r.get('coverage') for r in self.rows),
                           'pixel_weighted': (self._n_eval / self._n_gt) if self._n_gt else float('nan')}
        out['edges'] = self._edge_summary()
        curves = self.mean_curves()
        if curves is not None:
            out['confidence'] = {
                'ause_frame_mean': _nanmean(r.get('ause') for r in self.rows),
                'ause_of_mean_curve': ause(curves),
                'aurg_of_mean_curve': aurg(curves),
                'confident_half_ratio_frame_mean': _nanmean(r.get('confident_half_ratio') for r in self.rows),
                'confident_half_ratio_pooled': self.pooled_confident_half_ratio(),
                'mean_confidence': _nanmean(r.get('mean_confidence') for r in self.rows),
            }
            if self._pooled:
                out['calibration'] = calibration_summary(np.concatenate([c for _, c in self._pooled]),
                                                         np.concatenate(self._pooled_hit))
        if self._temporal:
            vals = [v for v, n in self._temporal if n > 0 and np.isfinite(v)]
            tot = sum(n for v, n in self._temporal if n > 0 and np.isfinite(v))
            out['temporal_consistency'] = {
                'pair_mean': float(np.mean(vals)) if vals else float('nan'),
                'pixel_weighted': (sum(v * n for v, n in self._temporal if n > 0 and np.isfinite(v)) / tot)
                if tot else float('nan'),
                'num_pairs': len(vals)}
        return out
