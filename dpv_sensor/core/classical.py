"""A classical, training-free measurement model: plane-sweep zero-mean NCC -> log-DPV.

This is the baseline of the project, the fallback when no network weights load, and it works on
real images. Per reference frame:

1. RGB in [0, 1] -> grey; grey box-filtered down by ``downscale`` (average pooling, so the volume
   has the networks' resolution, e.g. 1/4) with K scaled accordingly (pixel-centre convention).
2. Three channels at that resolution: grey and its x / y central-difference gradients.
3. Every source view is warped onto the D planes of the reference (:func:`plane_sweep_warp`);
   per plane and pixel the zero-mean normalised cross-correlation (ZNCC) of a ``patch x patch``
   window is computed per channel and averaged over channels. A window that reaches outside the
   source image is invalid for that view.
4. Scores are averaged over the source views that are valid there; planes that no view sees take
   the mean score of their ray (neutral). Scores lie in [-1, 1], higher = better match.
5. Cost aggregation: the score volume is box-filtered per plane over ``aggregate x aggregate``
   pixels (borders averaged over the pixels inside), which spreads evidence into weakly textured
   neighbours (fronto-parallel smoothness prior).
6. ``logp = log_softmax(score / temperature)`` over the planes.

:func:`select_source_frames` picks the window's source frames by camera baseline rather than by a
fixed frame offset, so the parallax does not depend on the camera speed.

Cost is dominated by ``num_src * D`` bilinear samples and three box filters per channel over the
(D, H/s, W/s) volume; see ``python -m dpv_sensor.benchmarks.core``.
"""
from __future__ import annotations

from typing import Tuple

import torch
import torch.nn.functional as F

from dpv_sensor import params as _params
from dpv_sensor.core.dpv import depth_planes
from dpv_sensor.core.geometry import plane_sweep_warp, scale_intrinsics

__all__ = ['ClassicalMeasurement', 'select_source_frames', 'to_grey', 'box_downscale', 'grey_features']


def to_grey(img_b3hw: torch.Tensor) -> torch.Tensor:
    """ITU-R BT.601 luma of RGB images (B, 3, H, W) -> (B, 1, H, W); grey input passes through."""
    if img_b3hw.shape[1] == 1:
        return img_b3hw
    w = torch.tensor([0.299, 0.587, 0.114], dtype=img_b3hw.dtype, device=img_b3hw.device)
    return (img_b3hw * w.reshape(1, 3, 1, 1)).sum(1, keepdim=True)


def box_downscale(img_bchw: torch.Tensor, s: int) -> torch.Tensor:
    """Average ``s x s`` blocks (anti-aliased decimation); trailing rows/cols that do not fill a
    block are dropped, which leaves the pixel-centre mapping ``u = s*u' + (s-1)/2`` exact."""
    return img_bchw if s == 1 else F.avg_pool2d(img_bchw, s, s)


def grey_features(grey_b1hw: torch.Tensor) -> torch.Tensor:
    """(B, 3, H, W): grey, d/dx and d/dy (central differences, replicated borders)."""
    p = F.pad(grey_b1hw, (1, 1, 1, 1), mode='replicate')
    gx = 0.5 * (p[:, :, 1:-1, 2:] - p[:, :, 1:-1, :-2])
    gy = 0.5 * (p[:, :, 2:, 1:-1] - p[:, :, :-2, 1:-1])
    return torch.cat([grey_b1hw, gx, gy], 1)


def _box(x: torch.Tensor, k: int) -> torch.Tensor:
    """Mean over a k x k window of the last two dims (zero padding, divided by k*k).

    Running sums along each axis (cumsum), i.e. O(1) per pixel whatever k; same result as
    ``avg_pool`` with ``count_include_pad=True``.
    """
    if k == 1:
        return x
    r = k // 2
    p = F.pad(x, (r + 1, r)).cumsum(-1)
    y = p[..., k:] - p[..., :-k]
    p = F.pad(y.transpose(-1, -2), (r + 1, r)).cumsum(-1)
    y = (p[..., k:] - p[..., :-k]).transpose(-1, -2)
    return y / (k * k)


class ClassicalMeasurement:
    """Plane-sweep ZNCC measurement model (no training).

    Args:
        d_min, d_max: depth range of the planes (metres).
        num_planes: D, planes uniform in inverse depth.
        temperature: softmax temperature on ZNCC scores in [-1, 1] (lower = peakier DPVs).
        patch: odd ZNCC window size, in volume pixels.
        aggregate: odd size of the box filter applied to the score volume per plane (1 = off).
        downscale: integer factor from the input image to the volume (4 = the networks' 1/4).
        eps: variance regulariser (in grey-level^2 units, images in [0, 1]); textureless windows
            get scores near 0 and hence near-uniform, low-confidence DPVs.
    """

    def __init__(self, d_min: float = _params.default('d_min'), d_max: float = _params.default('d_max'),
                 num_planes: int = _params.default('num_planes'),
                 temperature: float = 0.07, patch: int = 5, downscale: int = 4, eps: float = 1e-4,
                 aggregate: int = 5):
        if patch < 1 or patch % 2 == 0:
            raise ValueError(f'patch must be a positive odd integer, got {patch}')
        if aggregate < 1 or aggregate % 2 == 0:
            raise ValueError(f'aggregate must be a positive odd integer, got {aggregate}')
        if downscale < 1 or int(downscale) != downscale:
            raise ValueError(f'downscale must be a positive integer, got {downscale}')
        if temperature <= 0:
            raise ValueError(f'temperature must be positive, got {temperature}')
        self.d_min, self.d_max, self.num_planes = float(d_min), float(d_max), int(num_planes)
        self.temperature, self.patch, self.eps = float(temperature), int(patch), float(eps)
        self.downscale, self.aggregate = int(downscale), int(aggregate)

    def depths(self, dtype=torch.float32, device=None) -> torch.Tensor:
        """The plane depths (D,)."""
        return depth_planes(self.d_min, self.d_max, self.num_planes, dtype=dtype, device=device)

    def volume_intrinsics(self, K_b33: torch.Tensor) -> torch.Tensor:
        """K of the volume grid for a full-image K."""
        s = 1.0 / self.downscale
        return scale_intrinsics(K_b33, s, s)

    def features(self, img_b3hw: torch.Tensor) -> torch.Tensor:
        """(B, 3, H/s, W/s) grey + gradient channels at volume resolution."""
        return grey_features(box_downscale(to_grey(img_b3hw), self.downscale))

    def score_volume(self, ref_b3hw: torch.Tensor, srcs_bn3hw: torch.Tensor, K_b33: torch.Tensor,
                     T_src_ref_bn44: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """ZNCC scores averaged over valid views.

        Returns (score_bdhw in [-1, 1], nvalid_bdhw = number of views valid per voxel, K_volume).
        """
        B, N = srcs_bn3hw.shape[:2]
        dt, dev = ref_b3hw.dtype, ref_b3hw.device
        K_vol = self.volume_intrinsics(K_b33.to(dt).expand(B, 3, 3))
        depths = self.depths(dt, dev)
        k = self.patch
        fr = self.features(ref_b3hw)                                      # B,C,h,w
        h, w = fr.shape[-2:]
        fr5 = fr[:, :, None]                                              # B,C,1,h,w
        mu_a = _box(fr5, k)
        var_a = (_box(fr5 * fr5, k) - mu_a * mu_a).clamp_min(0.0)
        fs = self.features(srcs_bn3hw.reshape(B * N, *srcs_bn3hw.shape[2:])).reshape(B, N, 3, h, w)
        total = torch.zeros(B, self.num_planes, h, w, dtype=dt, device=dev)
        count = torch.zeros_like(total)
        for n in range(N):
            warped, valid = plane_sweep_warp(fs[:, n], K_vol, K_vol, T_src_ref_bn44[:, n].to(dt), depths)
            mu_b = _box(warped, k)
            var_b = (_box(warped * warped, k) - mu_b * mu_b).clamp_min(0.0)
            cov = _box(warped * fr5, k) - mu_a * mu_b
            ncc = (cov / torch.sqrt((var_a + self.eps) * (var_b + self.eps))).mean(1)   # B,D,h,w
            if k > 1:  # the whole window must lie inside the source image
                valid = -F.max_pool2d(-valid.to(dt).reshape(B, -1, h, w), k, 1, k // 2) > 0.5
            vf = valid.to(dt)
            total = total + ncc * vf
            count = count + vf
        seen = count > 0
        score = torch.where(seen, total / count.clamp_min(1.0), torch.zeros_like(total))
        nseen = seen.to(dt).sum(1, keepdim=True)
        ray_mean = score.sum(1, keepdim=True) / nseen.clamp_min(1.0)
        score = torch.where(seen, score, ray_mean.expand_as(score))
        if self.aggregate > 1:
            a = self.aggregate
            score = F.avg_pool3d(score[:, None], (1, a, a), stride=1, padding=(0, a // 2, a // 2),
                                 count_include_pad=False)[:, 0]
        return score, count, K_vol

    def __call__(self, ref_b3hw: torch.Tensor, srcs_bn3hw: torch.Tensor, K_b33: torch.Tensor,
                 T_src_ref_bn44: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """Measurement DPV of the reference frame.

        Args:
            ref_b3hw: (B, 3, H, W) reference RGB in [0, 1] (1 channel = grey also accepted).
            srcs_bn3hw: (B, N, 3, H, W) source frames of the window.
            K_b33: (B, 3, 3) intrinsics of the full image.
            T_src_ref_bn44: (B, N, 4, 4) maps reference-camera points into each source camera.
        Returns:
            (logp_bdhw at (H/downscale, W/downscale), K_volume_b33).
        """
        logp, _, K_vol = self.measure_with_views(ref_b3hw, srcs_bn3hw, K_b33, T_src_ref_bn44)
        return logp, K_vol

    def measure_with_views(self, ref_b3hw: torch.Tensor, srcs_bn3hw: torch.Tensor, K_b33: torch.Tensor,
                           T_src_ref_bn44: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """As :meth:`__call__`, and the number of source views valid per voxel: (logp_bdhw, nvalid_bdhw,
        K_volume_b33)."""
        score, count, K_vol = self.score_volume(ref_b3hw, srcs_bn3hw, K_b33, T_src_ref_bn44)
        return torch.log_softmax(score / self.temperature, dim=1), count, K_vol


def select_source_frames(positions_n3, ref: int, baselines=(-0.3, -0.15, 0.15, 0.3)) -> list:
    """Indices of source frames for reference frame ``ref`` chosen by camera baseline.

    For each signed target baseline b (metres; b < 0 searches frames before ``ref``, b > 0 after),
    takes the frame whose camera centre is closest to |b| away from the reference's. Duplicates are
    dropped; directions with no frames contribute nothing. ``positions_n3``: (N, 3) camera centres
    (e.g. ``T_world_cam[:, :3, 3]``).
    """
    pos = torch.as_tensor(positions_n3, dtype=torch.float64)
    dist = (pos - pos[ref]).norm(dim=1)
    out = []
    for b in baselines:
        cand = torch.arange(ref + 1, pos.shape[0]) if b > 0 else torch.arange(0, ref)
        if cand.numel() == 0:
            continue
        j = int(cand[(dist[cand] - abs(b)).abs().argmin()])
        if j not in out:
            out.append(j)
    return out
