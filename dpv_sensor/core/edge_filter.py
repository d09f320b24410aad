"""Edge-aware depth refinement guided by the colour image (torch, no ROS).

Depth from a cost volume is blurred across object boundaries: the volume is built at a quarter of the
image resolution, and R-Net's upsampling only partly restores the edges. Image edges are sharp, and
depth edges nearly always sit on image edges. :func:`joint_weighted_median` replaces every depth by the
weighted median of its neighbourhood, weighted by confidence and by colour similarity to the centre
pixel. A guided filter (a locally affine model of depth in colour) was tried first and rejected: on a
step blurred over as many pixels as its window it only re-blends the blurred values, and it can place
depth between the two sides of an edge; the median chooses one side.

Cost: (2 radius / step + 1)^2 samples per pixel and one sort over them.
"""
from __future__ import annotations

import torch

__all__ = ['joint_weighted_median']


def joint_weighted_median(depth_bhw: torch.Tensor, weight_bhw: torch.Tensor, image_b3hw: torch.Tensor,
                          radius: int = 4, step: int = 4, sigma_colour: float = 0.08) -> torch.Tensor:
    """Depth (B, H, W) replaced by the weighted median of its neighbourhood (module docstring).

    Samples: every ``step``-th pixel within ``radius`` (Chebyshev) of each pixel. A sample's weight is its
    ``weight_bhw`` (the confidence) times ``exp(-|I_sample - I_centre|^2 / (2 sigma_colour^2))`` (colour
    distance in [0, 1] RGB): only samples on the pixel's own side of a colour edge count, and there the
    majority wins, so a depth step blurred over fewer than about ``radius`` pixels is pulled onto the
    colour edge, and isolated wrong pixels are replaced. A median never invents a depth between the two
    sides of an edge. Pixels with a non-finite or non-positive depth keep it and never vote.
    """
    if radius <= 0:
        return depth_bhw
    if image_b3hw.shape[-2:] != depth_bhw.shape[-2:]:
        raise ValueError(f'guide {tuple(image_b3hw.shape[-2:])} and depth {tuple(depth_bhw.shape[-2:])} differ')
    dtype = torch.float64 if depth_bhw.dtype == torch.float64 else torch.float32
    d = depth_bhw.to(dtype)
    ok = torch.isfinite(d) & (d > 0)
    v = torch.where(ok, d, torch.zeros_like(d))[:, None]
    w = torch.where(ok, weight_bhw.to(dtype).clamp_min(0.0) + 1e-6, torch.zeros_like(d))[:, None]
    img = image_b3hw.to(dtype)
    r, s = int(radius), max(int(step), 1)
    H, W = d.shape[-2:]
    pad = (r, r, r, r)
    vp = torch.nn.functional.pad(v, pad)                     # zero weight outside the image
    wp = torch.nn.functional.pad(w, pad)
    img_p = torch.nn.functional.pad(img, pad, mode='replicate')
    offs = range(-(r // s) * s, r + 1, s)
    vals, wts = [], []
    inv2s2 = 1.0 / (2.0 * sigma_colour * sigma_colour)
    for dy in offs:
        for dx in offs:
            ys, xs = r + dy, r + dx
            vals.append(vp[:, :, ys:ys + H, xs:xs + W])
            c = ((img_p[:, :, ys:ys + H, xs:xs + W] - img) ** 2).sum(1, keepdim=True)
            wts.append(wp[:, :, ys:ys + H, xs:xs + W] * torch.exp(-c * inv2s2))
    # samples last (contiguous): sorting many short rows is fast that way
    V = torch.cat(vals, 1).permute(0, 2, 3, 1).contiguous()          # B,H,W,N
    Wt = torch.cat(wts, 1).permute(0, 2, 3, 1).contiguous()
    V = torch.where(Wt > 0, V, torch.full_like(V, float('inf')))   # samples without weight sort last
    Vs, order = V.sort(-1)
    cw = Wt.gather(-1, order).cumsum(-1)
    k = (cw < 0.5 * cw[..., -1:]).sum(-1, keepdim=True).clamp(max=V.shape[-1] - 1)
    med = Vs.gather(-1, k)[..., 0]
    return torch.where(ok & torch.isfinite(med), med, d).to(depth_bhw.dtype)
