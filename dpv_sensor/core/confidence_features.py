"""Per-pixel cues of whether a published depth is right, beside the DPV's band mass: the maths of each, arrays in,
arrays out (torch only; no stream, no ROS). The estimator gathers them per keyframe
(``dpv_sensor.stream.confidence_features``); the confidence study (``dpv_sensor.studies.confidence_features``)
measures how well each ranks right from wrong and which carry from one sequence to another.

Every function returns (B, H, W) maps on the grid of its input. Conventions:

- ``entropy_share``: the DPV's entropy over log D (0 = one plane, 1 = uniform).
- ``second_mode_mass``: the largest mass of three adjacent planes outside the x``ratio`` band around the published
  depth (after the edge filter, where the band mass is taken around the depth before it; 0 = one mode; near the band
  mass = an ambiguous ray).
- ``image_texture``: the grey image's gradient magnitude (intensity per pixel, Sobel / 8) averaged over a box.
- ``photometric_residual``: the mean absolute colour difference between the reference and each source warped into
  it with the published depth, over the sources that see the pixel; with ``views`` (how many do).
- ``innovation_planes``: how far (in planes, inverse depth) the measurement's depth lies from the filter's
  prediction.
"""
from __future__ import annotations

import math
from typing import Optional, Tuple

import torch
import torch.nn.functional as F

from dpv_sensor.core import dpv as dpv_ops
from dpv_sensor.core.geometry import inverse_depth_index, warp_image_with_depth

__all__ = ['entropy_share', 'second_mode_mass', 'image_texture', 'photometric_residual', 'innovation_planes']

# the box (pixels) the texture is averaged over: about the receptive size of one volume cell
TEXTURE_BOX = 5


def entropy_share(logp_bdhw: torch.Tensor) -> torch.Tensor:
    """The DPV's entropy divided by log D, in [0, 1]."""
    D = logp_bdhw.shape[1]
    return dpv_ops.entropy(logp_bdhw.float()) / math.log(D)


def second_mode_mass(logp_bdhw: torch.Tensor, depths_d: torch.Tensor, depth_bhw: torch.Tensor,
                     ratio: float) -> torch.Tensor:
    """The largest mass of three adjacent planes outside the band [d / ratio, d * ratio] around ``depth_bhw``: each
    plane counts with the share of its index interval [k - 0.5, k + 0.5] that lies outside the band (the bin model
    of ``dpv.ratio_confidence``, so band mass + outside mass = 1 on the planes)."""
    p = torch.exp(logp_bdhw.float())
    D = p.shape[1]
    d = depths_d.to(p)
    a = inverse_depth_index(depth_bhw / ratio, d[0], d[-1], D)[:, None]
    b = inverse_depth_index(depth_bhw * ratio, d[0], d[-1], D)[:, None]
    lo, hi = torch.minimum(a, b), torch.maximum(a, b)
    k = torch.arange(D, dtype=p.dtype, device=p.device)[None, :, None, None]
    inside = (torch.minimum(k + 0.5, hi) - torch.maximum(k - 0.5, lo)).clamp(0.0, 1.0)
    q = p * (1.0 - inside)
    triple = F.avg_pool3d(q[:, None], kernel_size=(3, 1, 1), stride=1, padding=(1, 0, 0))[:, 0] * 3.0
    return triple.amax(1)


def image_texture(image_b3hw: torch.Tensor, box: int = TEXTURE_BOX) -> torch.Tensor:
    """Gradient magnitude of the grey image (its values per pixel; Sobel / 8), averaged over a ``box`` square."""
    grey = image_b3hw.float().mean(1, keepdim=True)
    kx = torch.tensor([[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]], device=grey.device) / 8.0
    g = F.pad(grey, (1, 1, 1, 1), mode='replicate')
    gx = F.conv2d(g, kx[None, None])
    gy = F.conv2d(g, kx.t()[None, None])
    mag = torch.sqrt(gx * gx + gy * gy)
    if box > 1:
        mag = F.avg_pool2d(F.pad(mag, (box // 2,) * 4, mode='replicate'), box, stride=1)
    return mag[:, 0]


def photometric_residual(ref_b3hw: torch.Tensor, src_n3hw: torch.Tensor, depth_bhw: torch.Tensor,
                         K_b33: torch.Tensor, T_src_ref_n44: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """(residual, views), each (1, H, W): the mean over the N sources that see the pixel at ``depth_bhw`` of the
    mean absolute colour difference between the reference and the source warped into it, and N's count. The
    residual is NaN where no source sees the pixel. One reference (B = 1); sources share the reference's K."""
    N = src_n3hw.shape[0]
    if N == 0:
        nan = torch.full_like(depth_bhw, float('nan'))
        return nan, torch.zeros_like(depth_bhw)
    depth = depth_bhw.expand(N, -1, -1)
    K = K_b33.expand(N, 3, 3)
    warped, valid = warp_image_with_depth(src_n3hw.float(), depth.float(), K.float(), K.float(),
                                          T_src_ref_n44.float())
    diff = (warped - ref_b3hw.float()).abs().mean(1)                     # N, H, W
    views = valid.float().sum(0, keepdim=True)
    total = (diff * valid).sum(0, keepdim=True)
    residual = torch.where(views > 0, total / views.clamp_min(1.0), torch.full_like(total, float('nan')))
    return residual, views


def innovation_planes(measured_logp_bdhw: torch.Tensor, predicted_logp_bdhw: Optional[torch.Tensor],
                      depths_d: torch.Tensor, readout: str) -> torch.Tensor:
    """|index(measured depth) - index(predicted depth)| in planes (inverse depth); NaN everywhere without a
    prediction (the first keyframe after a start or restart)."""
    if predicted_logp_bdhw is None:
        B, _D, H, W = measured_logp_bdhw.shape
        return torch.full((B, H, W), float('nan'), device=measured_logp_bdhw.device)
    d = depths_d.float()
    D = d.shape[0]
    a = inverse_depth_index(dpv_ops.depth_estimate(measured_logp_bdhw.float(), d, readout), d[0], d[-1], D)
    b = inverse_depth_index(dpv_ops.depth_estimate(predicted_logp_bdhw.float(), d, readout), d[0], d[-1], D)
    return (a - b).abs()
