"""Edge-aware depth refinement guided by the colour image (torch, no ROS).

Depth from a cost volume is blurred across object boundaries: the volume is built at a quarter of the
image resolution, and R-Net's upsampling only partly restores the edges. Image edges are sharp, and
depth edges nearly always sit on image edges. :func:`guided_depth_filter` is a confidence-weighted
guided filter (He et al., "Guided Image Filtering", 2010/2013) with the colour image as guide: in every
``(2r+1)^2`` window, inverse depth is modelled as an affine function of the colour, fitted by weighted
least squares with the published confidence as weight (unsure pixels borrow from sure ones nearby, not
the other way round); every pixel then averages the fits of the windows that contain it. Where the
colour is flat, the output is the weighted mean of the window (smoothing noise and terraces); across a
colour edge, each side follows its own fit, so a depth step is pulled onto the colour edge. ``eps``
(colour variance units, image in [0, 1]) sets how much colour contrast counts as an edge: larger
values smooth more and copy less texture into depth.

Cost: about a dozen box filters and a closed-form 3x3 solve per pixel, O(H W) whatever the radius.
"""
from __future__ import annotations

import torch

__all__ = ['box_mean', 'guided_depth_filter']


def _box_sum_1d(x: torch.Tensor, r: int, dim: int) -> torch.Tensor:
    """Sum over the window [i - r, i + r] along ``dim`` (cut at the ends), by a cumulative sum."""
    n = x.shape[dim]
    c = torch.cumsum(x, dim)
    zero = torch.zeros_like(c.narrow(dim, 0, 1))
    c = torch.cat([zero, c], dim)                                     # c[i] = sum of x[:i]
    hi = torch.arange(n, device=x.device).add(r + 1).clamp(max=n)
    lo = torch.arange(n, device=x.device).sub(r).clamp(min=0)
    return c.index_select(dim, hi) - c.index_select(dim, lo)


def box_mean(x_bchw: torch.Tensor, r: int) -> torch.Tensor:
    """Mean over the ``(2r+1)^2`` window around every pixel, windows cut at the border (same shape).
    O(H W) whatever ``r`` (cumulative sums)."""
    if r <= 0:
        return x_bchw
    H, W = x_bchw.shape[-2:]
    s = _box_sum_1d(_box_sum_1d(x_bchw, r, -2), r, -1)
    rows = _box_sum_1d(torch.ones(H, 1, dtype=x_bchw.dtype, device=x_bchw.device), r, 0)
    cols = _box_sum_1d(torch.ones(1, W, dtype=x_bchw.dtype, device=x_bchw.device), r, 1)
    return s / (rows * cols)


def guided_depth_filter(depth_bhw: torch.Tensor, weight_bhw: torch.Tensor, image_b3hw: torch.Tensor,
                        radius: int = 4, eps: float = 1e-3) -> torch.Tensor:
    """Depth (B, H, W) filtered in inverse depth with a weighted colour-guided filter (module docstring).

    ``weight_bhw``: per-pixel weight >= 0 (e.g. the confidence); pixels with a non-finite or non-positive
    depth get weight 0 and keep their value (NaN stays NaN). ``image_b3hw``: the guide, float in [0, 1],
    same H x W. ``radius`` 0 returns the input. Computed in float32 (float64 stays float64).
    """
    if radius <= 0:
        return depth_bhw
    if image_b3hw.shape[-2:] != depth_bhw.shape[-2:]:
        raise ValueError(f'guide {tuple(image_b3hw.shape[-2:])} and depth {tuple(depth_bhw.shape[-2:])} differ')
    dtype = torch.float64 if depth_bhw.dtype == torch.float64 else torch.float32
    d = depth_bhw.to(dtype)
    ok = torch.isfinite(d) & (d > 0)
    p = torch.where(ok, 1.0 / torch.where(ok, d, torch.ones_like(d)), torch.zeros_like(d))[:, None]   # B,1,H,W
    w = torch.where(ok, weight_bhw.to(dtype).clamp_min(0.0), torch.zeros_like(d))[:, None]
    w = w + 1e-6 * ok[:, None].to(dtype)                   # a window of zero-confidence pixels still averages
    I = image_b3hw.to(dtype)
    r = int(radius)

    mw = box_mean(w, r).clamp_min(1e-12)

    def wmean(x):
        return box_mean(w * x, r) / mw

    mI = wmean(I)                                          # B,3,H,W
    mp = wmean(p)                                          # B,1,H,W
    cov_Ip = wmean(I * p) - mI * mp                        # B,3,H,W
    pairs = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]
    var = {(i, j): wmean(I[:, i:i + 1] * I[:, j:j + 1]) - mI[:, i:i + 1] * mI[:, j:j + 1] for i, j in pairs}
    # solve (Sigma + eps I) a = cov per pixel in closed form (adjugate / determinant; Sigma + eps I is SPD)
    s00, s01, s02 = var[(0, 0)] + eps, var[(0, 1)], var[(0, 2)]
    s11, s12, s22 = var[(1, 1)] + eps, var[(1, 2)], var[(2, 2)] + eps
    c00 = s11 * s22 - s12 * s12
    c01 = s02 * s12 - s01 * s22
    c02 = s01 * s12 - s02 * s11
    c11 = s00 * s22 - s02 * s02
    c12 = s01 * s02 - s00 * s12
    c22 = s00 * s11 - s01 * s01
    det = s00 * c00 + s01 * c01 + s02 * c02
    v0, v1, v2 = cov_Ip[:, 0:1], cov_Ip[:, 1:2], cov_Ip[:, 2:3]
    a = torch.cat([c00 * v0 + c01 * v1 + c02 * v2,
                   c01 * v0 + c11 * v1 + c12 * v2,
                   c02 * v0 + c12 * v1 + c22 * v2], 1) / det                      # B,3,H,W
    b = mp - (a * mI).sum(1, keepdim=True)
    # average the fits of the windows containing each pixel, weighted by how much data each window had
    ma = box_mean(a * mw, r) / box_mean(mw, r)
    mb = box_mean(b * mw, r) / box_mean(mw, r)
    q = (ma * I).sum(1, keepdim=True) + mb
    inv_lo = p[ok[:, None]].min() if ok.any() else torch.tensor(1.0, dtype=dtype)
    inv_hi = p[ok[:, None]].max() if ok.any() else torch.tensor(1.0, dtype=dtype)
    q = q.clamp(inv_lo, inv_hi)[:, 0]                      # never outside the input's range
    return torch.where(ok, 1.0 / q, d).to(depth_bhw.dtype)
