"""Label-free losses for adapting the networks to a recording: photometric reprojection across the window with
the recording's poses, and the ties that keep the adapted weights near the shipped ones.

Photometric reprojection (Monodepth2's form, Godard et al. 2019, on the DPV's depth): the reference depth ``d``
read out of a DPV warps every source image of the window into the reference view
(:func:`dpv_sensor.core.geometry.warp_image_with_depth`), and each warped image is compared with the reference::

    pe(a, b) = alpha * (1 - SSIM(a, b)) / 2 + (1 - alpha) * |a - b|        (mean over the colour channels)
    e(u)     = min over sources s of pe(I_ref, warp(I_s; d, T_s_ref))(u)   (sources u falls outside are skipped)

The per-pixel minimum over the sources keeps a pixel that is occluded or out of view in one source from being
pushed to a wrong depth by that source. **Auto-masking**: a pixel counts only where the best warped error is
below the best error of the sources left *unwarped* (``min_s pe(I_ref, I_s)``): pixels that do not change
between the views (a static camera, texture-free surfaces, objects moving with the camera) say nothing about
depth and are left out.

Ties to the base weights, so that what the renderer taught (e.g. about texture-free walls, where the photometric
error is flat) survives the adaptation:

- :func:`parameter_penalty` (L2-SP): ``sum (theta - theta_base)^2`` over the adapted parameters;
- :func:`distillation`: ``KL(p_base || p)`` of the base network's DPV and the adapted one's, per pixel, mean.

The adapt loop (:mod:`.adapt_loop`) scores weights on held-out keyframes with :func:`score_error`: every pixel counts,
whichever the weights (one the depth sends out of every source counts with the error of the unwarped sources).
"""
from __future__ import annotations

from typing import Dict, Iterable, Optional, Tuple

import torch
import torch.nn.functional as F

from dpv_sensor.core import geometry

__all__ = ['SSIM_ALPHA', 'ssim_dissimilarity', 'photometric_error', 'reprojection_error', 'masked_mean',
           'parameter_penalty', 'distillation', 'downsample_image', 'plane_errors', 'photometric_evidence',
           'score_error', 'confidence_tie_weight']

SSIM_ALPHA = 0.85           # weight of the SSIM term (Monodepth2's)
_C1, _C2 = 0.01 ** 2, 0.03 ** 2
_FAR = 1e3                  # error given to a source a pixel does not reach (never the minimum when one does)


def ssim_dissimilarity(a_bchw: torch.Tensor, b_bchw: torch.Tensor) -> torch.Tensor:
    """``(1 - SSIM) / 2`` per pixel and channel over 3x3 windows (reflection padding), clamped to [0, 1]."""
    a = F.pad(a_bchw, (1, 1, 1, 1), mode='reflect')
    b = F.pad(b_bchw, (1, 1, 1, 1), mode='reflect')
    mu_a, mu_b = F.avg_pool2d(a, 3, 1), F.avg_pool2d(b, 3, 1)
    var_a = F.avg_pool2d(a * a, 3, 1) - mu_a ** 2
    var_b = F.avg_pool2d(b * b, 3, 1) - mu_b ** 2
    cov = F.avg_pool2d(a * b, 3, 1) - mu_a * mu_b
    num = (2 * mu_a * mu_b + _C1) * (2 * cov + _C2)
    den = (mu_a ** 2 + mu_b ** 2 + _C1) * (var_a + var_b + _C2)
    return torch.clamp((1 - num / den) / 2, 0.0, 1.0)


def photometric_error(a_b3hw: torch.Tensor, b_b3hw: torch.Tensor, alpha: float = SSIM_ALPHA) -> torch.Tensor:
    """``alpha * (1 - SSIM) / 2 + (1 - alpha) * L1``, mean over channels: (B, H, W)."""
    l1 = (a_b3hw - b_b3hw).abs().mean(1)
    if alpha <= 0:
        return l1
    return alpha * ssim_dissimilarity(a_b3hw, b_b3hw).mean(1) + (1 - alpha) * l1


def reprojection_error(ref_b3hw: torch.Tensor, srcs_bn3hw: torch.Tensor, depth_bhw: torch.Tensor,
                       K_b33: torch.Tensor, T_src_ref_bn44: torch.Tensor, automask: bool = True
                       ) -> Tuple[torch.Tensor, torch.Tensor]:
    """Per-pixel photometric reprojection error of ``depth_bhw`` and the pixels it counts on.

    ref_b3hw: (B, 3, H, W) reference image; srcs_bn3hw: (B, N, 3, H, W) the window's sources (same K);
    depth_bhw: (B, H, W) reference depth (metres; differentiable); T_src_ref_bn44: reference -> source.
    Returns (error (B, H, W): the minimum over the sources a pixel reaches, mask (B, H, W) bool: the pixel reaches
    a source and, with ``automask``, its warped error is below the unwarped one; see the module docstring).
    """
    B, N = srcs_bn3hw.shape[:2]
    errs, ident = [], []
    for s in range(N):
        src = srcs_bn3hw[:, s]
        warped, valid = geometry.warp_image_with_depth(src, depth_bhw, K_b33, K_b33, T_src_ref_bn44[:, s])
        e = photometric_error(ref_b3hw, warped)
        errs.append(torch.where(valid, e, torch.full_like(e, _FAR)))
        if automask:
            with torch.no_grad():
                ident.append(photometric_error(ref_b3hw, src))
    err, _ = torch.stack(errs, 1).min(1)
    mask = err < _FAR
    if automask:
        identity, _ = torch.stack(ident, 1).min(1)
        mask = mask & (err.detach() < identity)
    return err, mask


_PATCH = torch.tensor([(dx, dy) for dy in (-1, 0, 1) for dx in (-1, 0, 1)], dtype=torch.float32)   # 3x3, centre 4


def plane_errors(ref_b3hw: torch.Tensor, srcs_bn3hw: torch.Tensor, K_b33: torch.Tensor,
                 T_src_ref_bn44: torch.Tensor, depths_d: torch.Tensor, stride: int = 4,
                 alpha: float = SSIM_ALPHA) -> Tuple[torch.Tensor, torch.Tensor]:
    """The plane sweep's photometric error on the quarter-resolution DPV grid, from full-resolution images.

    For every grid pixel ``u = stride * j`` (the DPV's pixels) and plane depth ``d``, the 3x3 patch of the reference
    around u is back-projected onto the fronto-parallel plane at depth d, projected into each source and sampled
    there (bilinear); the error is ``alpha * (1 - SSIM) / 2 + (1 - alpha) * |centre difference|`` (mean over the
    colour channels), the minimum over the sources the patch centre reaches (``_FAR`` where none does).
    Returns (errors (B, D, h, w), identity (B, h, w): the same error of the sources left unwarped). No gradient:
    it is the evidence the DPV is scored against, not a prediction."""
    B, N = srcs_bn3hw.shape[:2]
    H, W = ref_b3hw.shape[-2:]
    h, w = -(-H // stride), -(-W // stride)
    dev, dt = ref_b3hw.device, ref_b3hw.dtype
    with torch.no_grad():
        ys, xs = torch.meshgrid(torch.arange(h, device=dev, dtype=dt) * stride,
                                torch.arange(w, device=dev, dtype=dt) * stride, indexing='ij')
        off = _PATCH.to(dev, dt)
        px = (xs.reshape(-1, 1) + off[:, 0]).clamp(0, W - 1)            # (hw, 9)
        py = (ys.reshape(-1, 1) + off[:, 1]).clamp(0, H - 1)
        P = h * w * 9
        norm = torch.tensor([2.0 / max(W - 1, 1), 2.0 / max(H - 1, 1)], device=dev, dtype=dt)
        ref_grid = torch.stack([px, py], -1).reshape(1, 1, P, 2).expand(B, 1, P, 2) * norm - 1.0
        ref_patch = F.grid_sample(ref_b3hw, ref_grid, align_corners=True).reshape(B, 3, 1, h * w, 9)
        pix = torch.stack([px.reshape(-1), py.reshape(-1), torch.ones(P, device=dev, dtype=dt)])     # 3,P
        rays = torch.linalg.inv(K_b33.to(dt)) @ pix                                                   # B,3,P
        d = depths_d.to(dev, dt).view(1, -1, 1, 1)
        D = d.shape[1]
        errs, ident = [], []
        for s in range(N):
            T = T_src_ref_bn44[:, s].to(dt)
            pts = (T[:, None, :3, :3] @ (rays[:, None] * d)) + T[:, None, :3, 3:]                     # B,D,3,P
            uvz = K_b33.to(dt)[:, None] @ pts
            z = uvz[:, :, 2]
            front = z > 1e-6
            uv = uvz[:, :, :2] / torch.where(front, z, torch.ones_like(z))[:, :, None]
            grid = uv.transpose(2, 3) * norm - 1.0                                                  # B,D,P,2
            inside = front & (grid.abs() <= 1.0).all(-1)
            sampled = F.grid_sample(srcs_bn3hw[:, s], grid.reshape(B, D, P, 2), align_corners=True)  # B,3,D,P
            e = _patch_error(ref_patch, sampled.reshape(B, 3, D, h * w, 9), alpha)                   # B,D,hw
            centre = inside.reshape(B, D, h * w, 9)[..., 4]
            errs.append(torch.where(centre, e, torch.full_like(e, _FAR)))
            same = F.grid_sample(srcs_bn3hw[:, s], ref_grid, align_corners=True).reshape(B, 3, 1, h * w, 9)
            ident.append(_patch_error(ref_patch, same, alpha)[:, 0])
        err = torch.stack(errs, 1).min(1).values.reshape(B, D, h, w)
        identity = torch.stack(ident, 1).min(1).values.reshape(B, h, w)
    return err, identity


def _patch_error(a: torch.Tensor, b: torch.Tensor, alpha: float) -> torch.Tensor:
    """SSIM + L1 error of 3x3 patches: a, b (B, 3, D, n, 9) -> (B, D, n), mean over the channels."""
    mu_a, mu_b = a.mean(-1), b.mean(-1)
    # the centred mean square, not Tensor.var: the same to 3e-8 and 5x faster over a trailing dimension of 9
    var_a = (a - mu_a[..., None]).square().mean(-1)
    var_b = (b - mu_b[..., None]).square().mean(-1)
    cov = (a * b).mean(-1) - mu_a * mu_b
    ssim = ((2 * mu_a * mu_b + _C1) * (2 * cov + _C2)) / ((mu_a ** 2 + mu_b ** 2 + _C1) * (var_a + var_b + _C2))
    dis = torch.clamp((1 - ssim) / 2, 0.0, 1.0)
    l1 = (a[..., 4] - b[..., 4]).abs()
    return (alpha * dis + (1 - alpha) * l1).mean(1)


def photometric_evidence(logp_bdhw: torch.Tensor, errors_bdhw: torch.Tensor, identity_bhw: torch.Tensor,
                         sigma: float) -> torch.Tensor:
    """Negative log evidence of the images under a DPV, per pixel: ``-log sum_d p_d exp(-(e_d - e_best) / sigma)``
    (0 for a DPV with all its mass on the best plane); mean over the pixels that move (best plane error below the
    unwarped one) and reach a source.

    The gradient moves each ray's probability towards ``p_d exp(-e_d / sigma)`` (a Bayes update of the DPV by the
    photometric likelihood): where the errors are flat over the planes (no texture) there is no gradient and the
    networks' prior stays; where one plane explains the patch, mass moves to it."""
    e = errors_bdhw.to(logp_bdhw.dtype)
    best = e.min(1).values
    mask = (best < _FAR) & (best < identity_bhw)
    loglik = -(e - best[:, None]) / sigma
    loglik = torch.where(e < _FAR, loglik, torch.full_like(loglik, -1e4))
    nll = -torch.logsumexp(logp_bdhw + loglik, dim=1)
    return masked_mean(nll, mask)


def score_error(ref_b3hw: torch.Tensor, srcs_bn3hw: torch.Tensor, depth_bhw: torch.Tensor, K_b33: torch.Tensor,
                T_src_ref_bn44: torch.Tensor) -> torch.Tensor:
    """The per-pixel error a held-out score averages, over every pixel whatever the depth: the reprojection error
    (minimum over the sources the pixel reaches, no auto-mask), or where the depth sends the pixel out of every
    source, the error of the sources left unwarped (what a pixel without a usable depth explains). (B, H, W)."""
    err, reach = reprojection_error(ref_b3hw, srcs_bn3hw, depth_bhw, K_b33, T_src_ref_bn44, automask=False)
    identity = torch.stack([photometric_error(ref_b3hw, srcs_bn3hw[:, s]) for s in range(srcs_bn3hw.shape[1])],
                           1).min(1).values
    return torch.where(reach, err, identity)


def masked_mean(x_bhw: torch.Tensor, mask_bhw: torch.Tensor) -> torch.Tensor:
    """Mean of ``x`` over the mask (0 with a graph to ``x`` when the mask is empty)."""
    m = mask_bhw.to(x_bhw.dtype)
    return (x_bhw * m).sum() / m.sum().clamp_min(1.0)


def downsample_image(image_b3hw: torch.Tensor, factor: int = 4) -> torch.Tensor:
    """The image on the quarter-resolution DPV grid: volume pixel j sits on image pixel ``factor * j``
    (``dnet.feature_intrinsics``), so each is the mean of the (factor + 1)^2 pixels centred there."""
    k = factor + 1
    return F.avg_pool2d(image_b3hw, k, factor, padding=k // 2, count_include_pad=False)


def parameter_penalty(named_params: Iterable[Tuple[str, torch.Tensor]], base: Dict[str, torch.Tensor]
                      ) -> torch.Tensor:
    """L2-SP: ``sum over the adapted parameters of ||theta - theta_base||^2`` (a scalar with a graph)."""
    total: Optional[torch.Tensor] = None
    for name, p in named_params:
        if not p.requires_grad:
            continue
        d = ((p - base[name].to(p.device, p.dtype)) ** 2).sum()
        total = d if total is None else total + d
    return total if total is not None else torch.zeros(())


def distillation(logp_bdhw: torch.Tensor, logp_base_bdhw: torch.Tensor,
                 weight_bhw: Optional[torch.Tensor] = None) -> torch.Tensor:
    """``KL(p_base || p)`` over the planes, mean over pixels: keeps the adapted DPV (shape and width, hence the
    confidence) near the base network's where the photometric error does not say otherwise. ``weight_bhw``: a
    weight per pixel (e.g. :func:`confidence_tie_weight`); the mean is then over all pixels of the weighted KL."""
    p_base = torch.exp(logp_base_bdhw)
    kl_bhw = (p_base * (logp_base_bdhw - logp_bdhw)).sum(1)
    return (kl_bhw if weight_bhw is None else kl_bhw * weight_bhw).mean()


def confidence_tie_weight(confidence_bhw: torch.Tensor, threshold: float) -> torch.Tensor:
    """How much a pixel's DPV is tied to the base network's: 0 up to the base's confidence ``threshold``, rising
    linearly to 1 at confidence 1. What the base network is sure of (depth its training taught it, texture-free
    surfaces included) stays; what it guessed is left to the recording's photometry."""
    if not 0.0 <= threshold < 1.0:
        raise ValueError(f'threshold must lie in [0, 1), got {threshold}')
    return ((confidence_bhw - threshold) / (1.0 - threshold)).clamp(0.0, 1.0)
