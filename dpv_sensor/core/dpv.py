"""Depth probability volumes (DPVs): planes, normalisation, depth, confidence, NLL.

A DPV ``p(d; u, v)`` is carried as log-probabilities ``logp_bdhw`` of shape (B, D, H, W): a
log-softmax over dim 1 across D fronto-parallel planes uniform in inverse depth, ordered by
ascending depth (index 0 = d_min, index D-1 = d_max). Everything is torch, batched and
differentiable, dtype/device agnostic.
"""
from __future__ import annotations

import math
from typing import Optional

import torch

from dpv_sensor import params as _params
from dpv_sensor.core.geometry import inverse_depth_index

__all__ = [
    'LOG_FLOOR', 'depth_planes', 'depth_to_index', 'index_to_depth', 'normalize_log', 'clamp_log',
    'uniform_log', 'expected_depth', 'expected_index', 'argmax_depth', 'confidence', 'entropy',
    'nll', 'valid_depth_mask', 'one_hot_log', 'READOUTS', 'quantile_index', 'median_depth',
    'relative_depth', 'depth_estimate', 'estimate_index', 'DEFAULT_READOUT', 'READOUT_CHOICES', 'resolve_readout',
    'ratio_confidence', 'published_confidence', 'CONFIDENCES', 'DEFAULT_CONFIDENCE', 'subplane_index',
    'subplane_depth', 'rescale_depth',
]

# Lowest log-probability we keep anywhere in the filter (e^-30 ~ 1e-13): a zero-probability
# prediction can then be overturned by a few measurements instead of locking a voxel forever.
LOG_FLOOR = -30.0


def depth_planes(d_min: float, d_max: float, D: int, dtype=torch.float32, device=None) -> torch.Tensor:
    """D plane depths (metres) uniform in inverse depth from d_min (index 0) to d_max (index D-1)."""
    if not (0 < d_min < d_max):
        raise ValueError(f'need 0 < d_min < d_max, got d_min={d_min}, d_max={d_max}')
    if D < 2:
        raise ValueError(f'need at least 2 planes, got D={D}')
    inv = torch.linspace(1.0 / d_min, 1.0 / d_max, D, dtype=torch.float64)
    depths = 1.0 / inv
    depths[0], depths[-1] = d_min, d_max
    return depths.to(dtype=dtype, device=device)


def depth_to_index(depth, d_min: float, d_max: float, D: int) -> torch.Tensor:
    """Fractional plane index of a depth (same shape): 0 at d_min, D-1 at d_max, linear in 1/depth.

    Depths outside [d_min, d_max] give indices outside [0, D-1]; non-positive depths give NaN.
    """
    depth = torch.as_tensor(depth)
    if not depth.is_floating_point():
        depth = depth.to(torch.get_default_dtype())
    return inverse_depth_index(depth, d_min, d_max, D)


def index_to_depth(index, d_min: float, d_max: float, D: int) -> torch.Tensor:
    """Depth of a (fractional) plane index: the inverse of :func:`depth_to_index`."""
    index = torch.as_tensor(index)
    if not index.is_floating_point():
        index = index.to(torch.get_default_dtype())
    inv = 1.0 / d_min + (1.0 / d_max - 1.0 / d_min) * index / (D - 1)
    return 1.0 / inv


def rescale_depth(logp_bdhw: torch.Tensor, log_scale_bhw: torch.Tensor, d_min: float, d_max: float,
                  floor: float = LOG_FLOOR) -> torch.Tensor:
    """The DPV of each pixel's depth multiplied by ``exp(log_scale)``: plane j, at depth ``z_j``, takes the
    probability the DPV gave ``z_j / s``, read between the two planes around it (linearly in probability), then
    renormalised. The end planes stand for everything beyond them: a depth read beyond the range reads the end
    plane, so a belief that everything is far stays far. Pixels whose log scale is exactly 0 or not finite keep
    their values bit for bit; a log scale of batch 1 applies to every DPV of the batch; ``floor``: as
    :func:`clamp_log`'s."""
    B, D, H, W = logp_bdhw.shape
    log_scale_bhw = log_scale_bhw.expand(B, H, W)
    log_scale_bhw = torch.where(torch.isfinite(log_scale_bhw), log_scale_bhw, torch.zeros_like(log_scale_bhw))
    z_d = index_to_depth(torch.arange(D, dtype=torch.float64, device=logp_bdhw.device), d_min, d_max, D)
    src = z_d.view(1, D, 1, 1) * torch.exp(-log_scale_bhw.to(torch.float64))[:, None]
    idx = depth_to_index(src, d_min, d_max, D).clamp(0, D - 1)
    i0 = idx.floor()
    w = (idx - i0).to(logp_bdhw.dtype)
    i0 = i0.long()
    i1 = (i0 + 1).clamp(max=D - 1)
    p0, p1 = logp_bdhw.gather(1, i0), logp_bdhw.gather(1, i1)
    out = clamp_log(torch.logaddexp(p0 + torch.log1p(-w), p1 + torch.log(w)), floor)
    return torch.where((log_scale_bhw == 0)[:, None], logp_bdhw, out)


def normalize_log(logits_bdhw: torch.Tensor) -> torch.Tensor:
    """Log-probabilities from unnormalised log-values (log-softmax over the plane dim 1)."""
    return torch.log_softmax(logits_bdhw, dim=1)


def clamp_log(logp_bdhw: torch.Tensor, floor: float = LOG_FLOOR) -> torch.Tensor:
    """Clamp log-probabilities at ``floor`` and renormalise (keeps energies finite and bounded)."""
    return normalize_log(logp_bdhw.clamp_min(floor))


def uniform_log(B: int, D: int, H: int, W: int, dtype=torch.float32, device=None) -> torch.Tensor:
    """The uniform DPV, log(1/D) everywhere."""
    return torch.full((B, D, H, W), -math.log(D), dtype=dtype, device=device)


def one_hot_log(index_bhw: torch.Tensor, D: int, peak: float = 0.0, floor: float = LOG_FLOOR) -> torch.Tensor:
    """A (numerically) one-hot DPV at integer plane indices: logits ``peak`` at the index, ``floor``
    elsewhere, normalised."""
    idx = index_bhw.long().clamp(0, D - 1)
    dtype = index_bhw.dtype if index_bhw.is_floating_point() else torch.get_default_dtype()
    logits = torch.full((idx.shape[0], D, *idx.shape[1:]), floor, dtype=dtype, device=idx.device)
    logits.scatter_(1, idx[:, None], peak)
    return normalize_log(logits)


def _planes(depths_d: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    return torch.as_tensor(depths_d, dtype=like.dtype, device=like.device)


def _view_d(depths_d: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    d = _planes(depths_d, like)
    return d.reshape(1, -1, 1, 1) if d.dim() == 1 else d[:, :, None, None]


def expected_depth(logp_bdhw: torch.Tensor, depths_d: torch.Tensor) -> torch.Tensor:
    """Paper eq. 1: ``d_hat(u, v) = sum_k p_k(u, v) * d_k``; shape (B, H, W)."""
    return (torch.exp(logp_bdhw) * _view_d(depths_d, logp_bdhw)).sum(1)


def expected_index(logp_bdhw: torch.Tensor, depths_d: torch.Tensor) -> torch.Tensor:
    """Fractional plane index of the expected depth (planes uniform in inverse depth)."""
    d = _planes(depths_d, logp_bdhw)
    D = logp_bdhw.shape[1]
    return inverse_depth_index(expected_depth(logp_bdhw, d), d[0], d[-1], D)


def argmax_depth(logp_bdhw: torch.Tensor, depths_d: torch.Tensor) -> torch.Tensor:
    """Depth of the most probable plane (MAP over the discrete planes); shape (B, H, W)."""
    return _planes(depths_d, logp_bdhw)[logp_bdhw.argmax(1)]


def quantile_index(logp_bdhw: torch.Tensor, q: float = 0.5) -> torch.Tensor:
    """Fractional plane index where the DPV's cumulative mass reaches ``q``; shape (B, H, W).

    Plane k's mass is taken as spread uniformly over the index interval ``[k - 0.5, k + 0.5]`` (the
    same model as :func:`confidence`), so the CDF is piecewise linear in the index and the quantile is
    exact under that model; the result is clamped to ``[0, D - 1]``. Differentiable in the
    probabilities (piecewise).

    The running sum goes plane by plane (each step one contiguous (B, H, W) slice) and keeps only what the
    quantile needs: how many planes the CDF stays below ``q`` (it never decreases, so those are the first ones)
    and its value on the last of them before plane D - 1. Neither the CDF volume nor a volume of comparisons is
    stored: at 32 planes and 320x256 those temporaries (10 and 21 MB) cost more than the arithmetic, more
    still where the C library maps and unmaps each of them. The figures equal those of a full cumulative sum.
    """
    D = logp_bdhw.shape[1]
    p = torch.exp(logp_bdhw)
    acc = p[:, 0]
    count = torch.zeros(acc.shape, dtype=torch.int32, device=acc.device)   # planes whose CDF is below q
    before = torch.zeros_like(acc)       # the CDF of the plane before the quantile's (0 before plane 0)
    for k in range(D):
        if k:
            acc = acc + p[:, k]
        below = acc < q
        count += below
        if k <= D - 2:                   # the quantile's plane is clamped to D - 1: its predecessor to D - 2
            before = torch.where(below, acc, before)
    k = count.clamp(max=D - 1).long()[:, None]                            # first plane whose CDF >= q
    pk = p.gather(1, k).clamp_min(torch.finfo(p.dtype).tiny)
    f = k.to(p.dtype) - 0.5 + ((q - before[:, None]) / pk).clamp(0.0, 1.0)
    return f[:, 0].clamp(0.0, D - 1.0)


def median_depth(logp_bdhw: torch.Tensor, depths_d: torch.Tensor) -> torch.Tensor:
    """Median depth of every ray (minimises the expected absolute error); shape (B, H, W)."""
    d = _planes(depths_d, logp_bdhw)
    return index_to_depth(quantile_index(logp_bdhw), d[0], d[-1], logp_bdhw.shape[1])


def relative_depth(logp_bdhw: torch.Tensor, depths_d: torch.Tensor) -> torch.Tensor:
    """The depth that minimises the expected *relative* error ``E|x - d| / d`` under the DPV.

    Setting the derivative of ``sum_k p_k |x - d_k| / d_k`` to zero shows the minimiser is the median
    of the reweighted distribution ``p_k / d_k``: a depth sensor's error is specified relative to the
    range, and this is the Bayes estimate for that loss (and for abs_rel). Shape (B, H, W).
    """
    d = _planes(depths_d, logp_bdhw)
    reweighted = normalize_log(logp_bdhw - torch.log(d).reshape(1, -1, 1, 1))
    return index_to_depth(quantile_index(reweighted), d[0], d[-1], logp_bdhw.shape[1])


# How a DPV is turned into one depth per pixel. 'mean' is the paper's eq. 1 (the expectation, which
# minimises the expected squared error); 'median' minimises the expected absolute error; 'relative'
# minimises the expected relative error. Mean and median differ most where the DPV is wide or has two
# modes (occlusion edges, weak texture): the mean lands between the modes, a flying pixel, while the
# median and 'relative' stay on one of them.
READOUTS = ('mean', 'median', 'relative')
_READOUT_FN = {'mean': expected_depth, 'median': median_depth, 'relative': relative_depth}
# The node's default (params.py) is 'auto': 'relative' for a learned DPV, 'mean' for the classical one.
# Chosen on training scenes (rendered training seeds, TartanAir hospital); the held-out figures are in the
# README. A classical NCC volume is nearly flat on weak texture, and reweighting a flat DPV by 1/d (or
# taking its median) moves those pixels to the nearest planes, where its mean stays mid-range.
DEFAULT_READOUT = _params.default('depth_readout')
READOUT_CHOICES = _params.choices('depth_readout')      # what depth_readout accepts (the settings table's list)


def resolve_readout(readout: str, learned: bool) -> str:
    """The readout to use: ``readout`` itself, or for 'auto' 'relative' (learned) / 'mean' (classical)."""
    if readout == 'auto':
        return 'relative' if learned else 'mean'
    if readout not in READOUTS:
        raise ValueError(f"readout must be 'auto' or one of {READOUTS}, got {readout!r}")
    return readout


def depth_estimate(logp_bdhw: torch.Tensor, depths_d: torch.Tensor, readout: str = 'mean') -> torch.Tensor:
    """One depth per ray with the given readout (one of :data:`READOUTS`); shape (B, H, W)."""
    try:
        fn = _READOUT_FN[readout]
    except KeyError:
        raise ValueError(f'readout must be one of {READOUTS}, got {readout!r}') from None
    return fn(logp_bdhw, depths_d)


def estimate_index(logp_bdhw: torch.Tensor, depths_d: torch.Tensor, readout: str = 'mean') -> torch.Tensor:
    """Fractional plane index of :func:`depth_estimate`; shape (B, H, W)."""
    d = _planes(depths_d, logp_bdhw)
    return inverse_depth_index(depth_estimate(logp_bdhw, d, readout), d[0], d[-1], logp_bdhw.shape[1])


def subplane_index(logp_bdhw: torch.Tensor, index_bhw: torch.Tensor) -> torch.Tensor:
    """A readout index refined below the plane spacing; shape (B, H, W).

    A peaked DPV puts nearly all its mass on one plane, and every readout above then lands on (or next
    to) that plane's centre: a smooth slanted surface comes out as terraces one plane apart. The
    log-probabilities of a peak are close to a parabola in the index (a Gaussian in inverse depth), so
    the vertex of the parabola through the mode and its two neighbours says where between planes the
    peak lies (as sub-pixel stereo refines a disparity). The readout is shifted by the vertex's offset
    from the mode's plane (at most half a plane), weighted by the mass of those three planes: a peaked
    DPV moves its readout onto the vertex, a wide one keeps its readout (and the readout's own choice,
    e.g. the relative readout's lean towards the camera, is kept either way). The mode is the most
    probable plane among the three nearest to ``index``; where it is not a local maximum or lies on the
    first or last plane, ``index`` is returned unchanged (NaN stays NaN).
    """
    D = logp_bdhw.shape[1]
    if D < 3:
        return index_bhw
    idx = index_bhw.to(logp_bdhw.dtype)
    k0 = torch.nan_to_num(idx, nan=1.0).round().clamp(1, D - 2).long()[:, None]   # B,1,H,W (NaN stays NaN below)
    trio = torch.cat([logp_bdhw.gather(1, k0 + o) for o in (-1, 0, 1)], 1)  # B,3,H,W
    k = (k0 + trio.argmax(1, keepdim=True) - 1).clamp(1, D - 2)
    lm, l0, lp = (logp_bdhw.gather(1, k + o)[:, 0] for o in (-1, 0, 1))
    curv = lm - 2.0 * l0 + lp
    peak = (l0 >= lm) & (l0 >= lp) & (curv < 0)
    offset = torch.where(peak, 0.5 * (lm - lp) / torch.where(peak, curv, -torch.ones_like(curv)),
                         torch.zeros_like(curv)).clamp(-0.5, 0.5)
    mass = torch.where(peak, torch.exp(lm) + torch.exp(l0) + torch.exp(lp), torch.zeros_like(curv)).clamp(0.0, 1.0)
    # a peaked readout sits near the mode's centre, so (k + offset) - k is the correction it lacks
    target = k[:, 0].to(idx.dtype) + offset
    return idx + mass * (target - idx).clamp(-0.5, 0.5) * (idx - k[:, 0].to(idx.dtype)).abs().le(0.5).to(idx.dtype)


def subplane_depth(logp_bdhw: torch.Tensor, depths_d: torch.Tensor, depth_bhw: torch.Tensor) -> torch.Tensor:
    """:func:`subplane_index` applied to a depth readout: depth in, refined depth out (B, H, W)."""
    d = _planes(depths_d, logp_bdhw)
    D = logp_bdhw.shape[1]
    idx = inverse_depth_index(depth_bhw.to(logp_bdhw.dtype), d[0], d[-1], D)
    return index_to_depth(subplane_index(logp_bdhw, idx), d[0], d[-1], D).to(depth_bhw.dtype)


def _gauss_integral(u: torch.Tensor) -> torch.Tensor:
    """``u Phi(u) + phi(u)``: the antiderivative of the standard normal CDF ``Phi``."""
    return u * 0.5 * (1.0 + torch.erf(u * (0.5 ** 0.5))) + torch.exp(-0.5 * u * u) * (2.0 * math.pi) ** -0.5


def _mass_in_index_window(logp_bdhw: torch.Tensor, lo_b1hw: torch.Tensor, hi_b1hw: torch.Tensor,
                          sigma_b1hw: Optional[torch.Tensor] = None) -> torch.Tensor:
    """DPV mass inside the fractional index window [lo, hi], plane k covering [k - 0.5, k + 0.5] with its mass
    spread uniformly (so uniform in inverse depth). (B, H, W) in [0, 1].

    With ``sigma_b1hw`` (planes, per pixel) the DPV is first convolved with a Gaussian of that std along the plane
    index (an extra, independent error of the index): plane k then puts ``int_{k-1/2}^{k+1/2} [Phi((hi - x) / s) -
    Phi((lo - x) / s)] dx`` inside the window, which is ``s [G((hi - k + 1/2) / s) - G((hi - k - 1/2) / s) - G((lo -
    k + 1/2) / s) + G((lo - k - 1/2) / s)]`` with ``G(u) = u Phi(u) + phi(u)``; s -> 0 gives the plain overlap.
    Eight transcendental functions per plane and pixel: meant for the volume resolution (the estimator applies
    the ratio it gives there to the full-resolution confidence)."""
    D = logp_bdhw.shape[1]
    k = torch.arange(D, dtype=logp_bdhw.dtype, device=logp_bdhw.device).reshape(1, D, 1, 1)
    overlap = (torch.minimum(k + 0.5, hi_b1hw) - torch.maximum(k - 0.5, lo_b1hw)).clamp(0.0, 1.0)
    if sigma_b1hw is not None:
        # beyond D planes the widened DPV is flat across any band; the cap also keeps the differences of G exact
        s = sigma_b1hw.to(logp_bdhw.dtype).nan_to_num(nan=0.0, posinf=float(D)).clamp(0.0, float(D))
        s_safe = s.clamp_min(1e-3)

        def edge(c):
            return s_safe * (_gauss_integral((c - k + 0.5) / s_safe) - _gauss_integral((c - k - 0.5) / s_safe))
        widened = (edge(hi_b1hw) - edge(lo_b1hw)).clamp(0.0, 1.0)
        overlap = torch.where(s > 1e-3, widened, overlap)
    return (torch.exp(logp_bdhw) * overlap).sum(1).clamp(0.0, 1.0)


def confidence(logp_bdhw: torch.Tensor, depths_d: torch.Tensor, readout: str = 'mean',
               depth_bhw: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Paper eq. 2 made comparable across planes: probability mass within +-1 bin of the estimate.

    With ``f`` the fractional plane index of the depth estimate (eq. 1 for ``readout='mean'``, else
    :func:`depth_estimate` with that readout) and plane k taken to cover the index interval
    ``[k - 0.5, k + 0.5]`` with its mass spread uniformly, the confidence is the mass of the DPV
    inside the index window ``[f - 1, f + 1]`` (one plane spacing, in inverse depth, either side of
    the estimate):

        C = sum_k p_k * |[k - 0.5, k + 0.5] ∩ [f - 1, f + 1]|.

    So C lies in [0, 1]; a one-hot DPV gives 1, mass split between two neighbouring planes gives
    (nearly) 1 (exactly when the estimate falls at their midpoint in index); the uniform DPV gives
    2/D away from the ends (less near the ends, where the window is cut).
    Unlike the raw ``p(d_hat)`` of a single bin, it does not drop just because the estimate sits
    between two planes. ``depth_bhw``: the estimate when the caller already has it (it is not read out
    again). Shape (B, H, W); differentiable in the probabilities.
    """
    B, D, H, W = logp_bdhw.shape
    d = _planes(depths_d, logp_bdhw)
    if depth_bhw is None:
        depth_bhw = depth_estimate(logp_bdhw, d, readout)
    f = inverse_depth_index(depth_bhw, d[0], d[-1], D)[:, None]             # B,1,H,W
    return _mass_in_index_window(logp_bdhw, f - 1.0, f + 1.0)


def ratio_confidence(logp_bdhw: torch.Tensor, depths_d: torch.Tensor, depth_bhw: torch.Tensor,
                     ratio: float = _params.default('confidence_ratio'),
                     sigma_planes_bhw: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Probability under the DPV that the true depth d lies within a factor ``ratio`` of the estimate:
    ``P(max(d / d_hat, d_hat / d) < ratio)``, i.e. that the pixel counts as correct by the delta < ratio
    accuracy measure (delta < 1.25 by default). Same bin model as :func:`confidence` (plane k's mass spread
    uniformly in inverse depth over [k - 0.5, k + 0.5]); the part of the band beyond the first or last plane
    holds no mass. Unlike the +-1-plane window, whose width in depth grows with depth (planes are uniform in
    inverse depth), the band is the same relative width everywhere, so a DPV as wide in metres at 5 m as
    another at 1 m is less confident. (B, H, W) in [0, 1]; differentiable in the probabilities.

    ``sigma_planes_bhw``: an independent error of the measured plane index (std in planes per pixel, e.g. the pose
    uncertainty of ``dpv_sensor.core.pose_uncertainty``) that the probability accounts for: the DPV convolved with that
    Gaussian (see ``_mass_in_index_window``). A larger sigma never raises the confidence of a unimodal DPV centred
    in the band.
    """
    if not ratio > 1.0:
        raise ValueError(f'ratio must be > 1, got {ratio}')
    B, D, H, W = logp_bdhw.shape
    d = _planes(depths_d, logp_bdhw)
    lo = inverse_depth_index(depth_bhw / ratio, d[0], d[-1], D)[:, None]    # nearer -> smaller index
    hi = inverse_depth_index(depth_bhw * ratio, d[0], d[-1], D)[:, None]
    sig = None if sigma_planes_bhw is None else sigma_planes_bhw[:, None]
    return _mass_in_index_window(logp_bdhw, lo, hi, sig)


CONFIDENCES = _params.choices('confidence')
DEFAULT_CONFIDENCE = _params.default('confidence')


def published_confidence(logp_bdhw: torch.Tensor, depths_d: torch.Tensor, depth_bhw: torch.Tensor,
                         mode: str = DEFAULT_CONFIDENCE, ratio: float = _params.default('confidence_ratio'),
                         sigma_planes_bhw: Optional[torch.Tensor] = None) -> torch.Tensor:
    """The confidence image the sensor publishes for the depth ``depth_bhw`` read out of a DPV (the node
    parameters ``confidence`` / ``confidence_ratio``): 'plane' = :func:`confidence` (mass within one plane
    of the estimate), 'ratio' = :func:`ratio_confidence` (probability that the depth is within a factor
    ``ratio`` of the truth). ``sigma_planes_bhw``: the pose uncertainty the ratio confidence accounts for (see
    :func:`ratio_confidence`; the plane confidence ignores it)."""
    if mode == 'plane':
        return confidence(logp_bdhw, depths_d, depth_bhw=depth_bhw)
    if mode == 'ratio':
        return ratio_confidence(logp_bdhw, depths_d, depth_bhw, ratio, sigma_planes_bhw)
    raise ValueError(f'confidence {mode!r} is not one of {list(CONFIDENCES)}')


def entropy(logp_bdhw: torch.Tensor) -> torch.Tensor:
    """Shannon entropy (nats) of every ray, shape (B, H, W)."""
    return -(torch.exp(logp_bdhw) * logp_bdhw).sum(1)


def valid_depth_mask(gt_bhw: torch.Tensor, d_min: float, d_max: float) -> torch.Tensor:
    """True where the GT depth is finite and inside [d_min, d_max] (0 = invalid is excluded)."""
    return torch.isfinite(gt_bhw) & (gt_bhw >= d_min) & (gt_bhw <= d_max)


def nll(logp_bdhw: torch.Tensor, depths_d: torch.Tensor, gt_bhw: torch.Tensor,
        mask_bhw: Optional[torch.Tensor] = None, reduction: str = 'mean') -> torch.Tensor:
    """Negative log-likelihood of the GT depth, interpolated between the two nearest planes.

    With GT fractional plane index ``f = i + w`` (i = floor(f), 0 <= w < 1) the per-pixel loss is

        nll = -((1 - w) * logp[i] + w * logp[i + 1]),

    i.e. the cross-entropy against the two-hot target that puts (1 - w, w) on the two planes that
    bracket the GT (its minimiser has expected index exactly f). A GT exactly on plane k gives
    ``-logp[k]``. Pixels whose GT is not valid (see :func:`valid_depth_mask` with the first/last
    plane as range) or where ``mask_bhw`` is False are excluded.

    reduction: 'mean' (over valid pixels; 0 when there are none), 'sum', or 'none' ((B, H, W),
    zero at excluded pixels).
    """
    B, D, H, W = logp_bdhw.shape
    d = torch.as_tensor(depths_d, dtype=logp_bdhw.dtype, device=logp_bdhw.device)
    gt = gt_bhw.to(logp_bdhw.dtype)
    valid = valid_depth_mask(gt, float(d[0]), float(d[-1]))
    if mask_bhw is not None:
        valid = valid & mask_bhw.bool()
    f = inverse_depth_index(torch.where(valid, gt, d[0].expand_as(gt)), d[0], d[-1], D)
    f = f.clamp(0.0, D - 1.0)
    i0 = f.floor().clamp(max=D - 2)
    w = (f - i0)[:, None]
    i0 = i0.long()[:, None]
    lp0 = torch.gather(logp_bdhw, 1, i0)
    lp1 = torch.gather(logp_bdhw, 1, i0 + 1)
    per_pixel = -((1.0 - w) * lp0 + w * lp1)[:, 0]
    per_pixel = torch.where(valid, per_pixel, torch.zeros_like(per_pixel))
    if reduction == 'none':
        return per_pixel
    if reduction == 'sum':
        return per_pixel.sum()
    if reduction == 'mean':
        return per_pixel.sum() / valid.sum().clamp_min(1).to(per_pixel.dtype)
    raise ValueError(f"reduction must be 'mean', 'sum' or 'none', got {reduction!r}")
