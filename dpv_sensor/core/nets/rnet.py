"""R-Net: image-guided U-Net upsampling of the quarter-resolution DPV (paper Sec. 3.3).

Layers (appendix table "R-Net structure", ``paper`` channel counts with D planes; ``lite`` only
narrows the two transposed-conv outputs ``up0``/``up1``, which are D in the table):

    conv_0        concat(DPV, D-Net fusion)  D+64 -> D+64, LeakyReLU, D+64 -> D+64, LeakyReLU   1/4
    trans_conv_0  4x4 transposed conv stride 2, D+64 -> D (up0), LeakyReLU                     1/2
    conv_1        concat(trans_conv_0, D-Net conv1 (32 ch))  D+32 -> D+32, LeakyReLU x 2        1/2
    trans_conv_1  4x4 transposed conv stride 2, D+32 -> D (up1), LeakyReLU                     1
    conv_2        concat(trans_conv_1, I_ref)  D+3 -> D+3, LeakyReLU; D+3 -> D, LeakyReLU; D -> D

Choices where the table is silent (documented):

* All convs have biases, no BN; LeakyReLU slope ``preset.leaky_slope`` (0.1); transposed convs use
  padding 1, so each exactly doubles the size.
* Odd sizes: the maps are ceil(H/4) -> ceil(H/2) -> H; each transposed conv's output (2x its input,
  never smaller than the next skip) is cropped at the bottom/right to the skip's size. Pixel (0, 0) is
  aligned at every level, consistent with the stride-2 convs of the D-Net (quarter pixel j = full 4j).
* Input DPV: the log-probabilities clamped at ``dpv.LOG_FLOOR`` (-30), so arbitrarily peaked inputs
  stay in range.
* Output: a residual around the table's network. The quarter-resolution log-DPV is upsampled exactly
  on the feature grid (full pixel u reads quarter coordinate u/4, bilinear in log space) and conv_2's
  output is added as a correction before the log-softmax. conv_2's last layer starts at zero, so an
  untrained R-Net is that plain upsampling (it cannot destroy a good DPV) and training learns the
  image-guided refinement. The table's channel counts and layers are unchanged.
"""
from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from dpv_sensor.core.dpv import LOG_FLOOR, normalize_log
from dpv_sensor.core.nets.dnet import FEATURE_STRIDE, _init_relu_conv
from dpv_sensor.core.nets.presets import Preset

__all__ = ['RNet', 'upsample_logp']


def upsample_logp(logp_bdhw: torch.Tensor, out_hw, stride: int = FEATURE_STRIDE,
                  normalize: bool = True) -> torch.Tensor:
    """Bilinear upsampling of a log-DPV on the stride-``stride`` grid: output pixel u reads the input
    at u/stride (edge-clamped). Log space, values clamped at LOG_FLOOR first; renormalised (log-softmax
    over dim 1) unless ``normalize=False``."""
    B, D, h, w = logp_bdhw.shape
    H, W = int(out_hw[0]), int(out_hw[1])
    x = logp_bdhw.clamp_min(LOG_FLOOR)
    dt, dev = x.dtype, x.device
    u = torch.arange(W, dtype=dt, device=dev) / stride
    v = torch.arange(H, dtype=dt, device=dev) / stride
    gx = 2.0 * u / max(w - 1, 1) - 1.0
    gy = 2.0 * v / max(h - 1, 1) - 1.0
    grid = torch.stack(torch.meshgrid(gy, gx, indexing='ij')[::-1], dim=-1)[None].expand(B, H, W, 2)
    up = F.grid_sample(x, grid, mode='bilinear', padding_mode='border', align_corners=True)
    return normalize_log(up) if normalize else up


def _conv(cin: int, cout: int) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, 3, padding=1, bias=True)


class RNet(nn.Module):
    """h(DPV, features, image) -> full-resolution log-DPV. See the module docstring."""

    def __init__(self, preset: Preset):
        super().__init__()
        p = preset
        D = p.num_planes
        s = p.leaky_slope
        c0 = D + p.feature_channels
        c1 = p.up0_channels + p.stem_channels
        c2 = p.up1_channels + 3
        act = lambda: nn.LeakyReLU(s, inplace=True)  # noqa: E731
        self.conv0 = nn.Sequential(_conv(c0, c0), act(), _conv(c0, c0), act())
        self.trans_conv0 = nn.Sequential(nn.ConvTranspose2d(c0, p.up0_channels, 4, stride=2, padding=1), act())
        self.conv1 = nn.Sequential(_conv(c1, c1), act(), _conv(c1, c1), act())
        self.trans_conv1 = nn.Sequential(nn.ConvTranspose2d(c1, p.up1_channels, 4, stride=2, padding=1), act())
        self.conv2 = nn.Sequential(_conv(c2, c2), act(), _conv(c2, D), act(), _conv(D, D))
        for m in self.modules():
            if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d)):
                _init_relu_conv(m, s)
        nn.init.zeros_(self.conv2[-1].weight)   # untrained R-Net == exact upsampling of the input DPV
        nn.init.zeros_(self.conv2[-1].bias)
        self.channels_last = False

    def forward(self, logp_bdhw: torch.Tensor, fusion_bchw: torch.Tensor, half_bchw: torch.Tensor,
                image_norm_b3hw: torch.Tensor) -> torch.Tensor:
        """logp (B,D,h,w) quarter res, fusion (B,F,h,w), half (B,S,ceil(H/2),ceil(W/2)),
        normalised image (B,3,H,W) -> log-DPV (B,D,H,W)."""
        H, W = image_norm_b3hw.shape[-2:]
        hh, hw = half_bchw.shape[-2:]
        if fusion_bchw.shape[-2:] != logp_bdhw.shape[-2:]:
            raise ValueError(f'DPV {tuple(logp_bdhw.shape[-2:])} and features {tuple(fusion_bchw.shape[-2:])} '
                             'differ in size')
        x = torch.cat([logp_bdhw.clamp_min(LOG_FLOOR).to(fusion_bchw.dtype), fusion_bchw], 1)
        if self.channels_last:
            x = x.contiguous(memory_format=torch.channels_last)
        x = self.trans_conv0(self.conv0(x))[..., :hh, :hw]
        x = self.conv1(torch.cat([x, half_bchw.to(x.dtype)], 1))
        x = self.trans_conv1(x)[..., :H, :W]
        delta = self.conv2(torch.cat([x, image_norm_b3hw.to(x.dtype)], 1))
        base = upsample_logp(logp_bdhw, (H, W), normalize=False)     # the final log-softmax normalises
        return normalize_log(base + delta).contiguous()
