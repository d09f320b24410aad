"""D-Net: the PSM-Net feature extractor and the plane-sweep cost volume -> log-DPV (paper Sec. 3.1).

Feature extractor (appendix table "D-Net structure"; channel counts below are the ``paper`` preset,
the ``lite`` preset only changes widths/block counts):

    conv0_1  3x3 conv 3->32 stride 2, ReLU                     1/2
    conv0_2  3x3 conv 32->32, ReLU                             1/2
    conv0_3  3x3 conv 32->32, ReLU                             1/2
    conv1    3 x [3x3 conv 32->32, ReLU, 3x3 conv 32->32] + skip   1/2   (R-Net's half-res input)
    conv1_1  3x3 conv 32->64 stride 2, ReLU                    1/4
    conv2    15 x [3x3 conv 64->64, ReLU, 3x3 conv] + skip     1/4
    conv2_1  3x3 conv 64->128, ReLU                            1/4
    conv3    2 x [3x3 conv 128->128, ReLU, 3x3 conv] + skip    1/4
    conv4    3 x [3x3 conv dil 2, ReLU, 3x3 conv dil 2] + skip 1/4
    branch1..4  avg_pool(64/32/16/8, stride = size), 1x1 conv 128->32, ReLU, bilinear up
    concat   (branch1, branch2, branch3, branch4, conv2, conv4) -> 320 channels
    fusion   3x3 conv 320->128, ReLU; 1x1 conv 128->64, ReLU   -> the 64-channel D-Net feature

Choices where the table is silent or inconsistent (documented, not guessed silently):

* Every convolution is a plain conv **with bias** and no batch norm (the table has no BN).
* The bracketed ``[conv, ReLU, conv] x n`` groups are PSM-Net's BasicBlocks: ``x + conv(relu(conv(x)))``
  with no ReLU after the sum (as in PSM-Net's BasicBlock, and as the table shows no final ReLU).
* The table lists conv1's input as ``conv0_2``; that would leave conv0_3 unused, so (as in PSM-Net,
  whose ``firstconv`` is the three conv0 layers) conv1 takes conv0_3's output.
* SPP pooling adapts to small inputs: a pool window larger than the quarter-resolution map is clamped
  to the map size per axis (so it becomes a global average), instead of failing. Windows that do not
  fit completely are dropped (floor), as PSM-Net's AvgPool2d does. Upsampling is bilinear with
  ``align_corners=False``.
* Without BN a deep residual stack would blow up at initialisation, so the second conv of every
  residual block is initialised with Kaiming-normal (linear gain) scaled by ``1/sqrt(blocks in stage)``
  (Fixup-like); convs followed by ReLU use Kaiming-normal for ReLU; all biases start at zero.

Geometry of the feature grid: every stride-2 layer is a 3x3 conv with padding 1, whose output pixel i
is centred on input pixel 2i. Hence quarter-resolution pixel j sits exactly on full-resolution pixel 4j,
the map has ceil(ceil(H/2)/2) = ceil(H/4) rows, and its intrinsics are ``fx/4, cx/4`` (see
:func:`feature_intrinsics`; the area-resize convention of ``geometry.scale_intrinsics`` would place it
0.375 quarter pixels (1.5 full-resolution pixels) off).

Cost volume (paper eq. 3): for every source view k and plane depth d,
``c_k(d, u, v) = mean_c |f_ref(c, u, v) - warp(f_k)(c, d, u, v)|`` (L1 over channels divided by the
channel count, so its scale does not depend on the preset's width), computed with
``geometry.plane_sweep_warp`` on the quarter-resolution features. The cost of a voxel is the average
of ``c_k`` over the views in which it is visible (``valid``), i.e. eq. 3's sum normalised by the number
of valid views, so border voxels seen by fewer views are not penalised. A voxel visible in no view gets
the per-pixel mean cost over its visible planes (neutral: it neither attracts nor repels probability);
a pixel visible on no plane gets a flat cost (uniform DPV). The DPV is
``log_softmax(-s * cost)`` over the planes with a learnt temperature ``s = exp(log_scale)``
(initialised to ``preset.softmax_scale_init``): eq. 3 writes ``softmax(L)``, the sign and the scale
are needed for a low cost to mean a high probability and for the DPV to be calibratable.
"""
from __future__ import annotations

import contextlib
import math
from typing import NamedTuple, Sequence

import torch
import torch.nn as nn
import torch.nn.functional as F

from dpv_sensor.core import geometry
from dpv_sensor.core.dpv import normalize_log
from dpv_sensor.core.nets.presets import Preset

__all__ = [
    'IMAGENET_MEAN', 'IMAGENET_STD', 'normalize_image', 'ImageFeatures', 'ResBlock2d', 'SPPBranch',
    'FeatureExtractor', 'L1Cost', 'CostVolume', 'feature_intrinsics', 'feature_size', 'FEATURE_STRIDE',
    'stack_source_features',
]

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
FEATURE_STRIDE = 4


def normalize_image(image_b3hw: torch.Tensor) -> torch.Tensor:
    """RGB in [0, 1] -> ImageNet-normalised (the usual input of a PSM-Net style extractor)."""
    mean = torch.tensor(IMAGENET_MEAN, dtype=image_b3hw.dtype, device=image_b3hw.device).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD, dtype=image_b3hw.dtype, device=image_b3hw.device).view(1, 3, 1, 1)
    return (image_b3hw - mean) / std


def feature_size(height: int, width: int) -> tuple:
    """(h, w) of the quarter-resolution feature map / DPV for an HxW input: (ceil(H/4), ceil(W/4))."""
    return (-(-int(height) // FEATURE_STRIDE), -(-int(width) // FEATURE_STRIDE))


def feature_intrinsics(K_b33: torch.Tensor, stride: int = FEATURE_STRIDE) -> torch.Tensor:
    """Intrinsics of the stride-``stride`` feature grid (and hence of the DPV): fx/s, cx/s.

    Built on ``geometry.scale_intrinsics(K, 1/s, 1/s)`` (area-resize convention,
    ``cx' = (cx + 0.5)/s - 0.5``) plus the shift ``0.5 * (1 - 1/s)`` that moves the grid to where the
    stride-2, padding-1 convolutions actually sample (quarter pixel j on full pixel s*j), so the result
    is exactly ``cx/s`` (and the same for y).
    """
    s = 1.0 / stride
    K = geometry.scale_intrinsics(K_b33, s, s)
    K = K.clone()
    K[..., 0, 2] = K[..., 0, 2] + 0.5 * (1.0 - s)
    K[..., 1, 2] = K[..., 1, 2] + 0.5 * (1.0 - s)
    return K


def no_autocast(device: torch.device):
    """Context that disables autocast on ``device`` (a no-op context for device types without autocast)."""
    if device.type in ('cpu', 'cuda', 'xpu', 'mps'):
        return torch.autocast(device_type=device.type, enabled=False)
    return contextlib.nullcontext()


class ImageFeatures(NamedTuple):
    """What the feature extractor gives for one (batch of) image(s).

    fusion: (B, feature_channels, ceil(H/4), ceil(W/4)) - the D-Net feature (cost volume, R-Net conv_0).
    half:   (B, stem_channels, ceil(H/2), ceil(W/2)) - conv1's output (R-Net conv_1 skip).
    """
    fusion: torch.Tensor
    half: torch.Tensor


def _conv3x3(cin: int, cout: int, stride: int = 1, dilation: int = 1) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, 3, stride=stride, padding=dilation, dilation=dilation, bias=True)


def _init_relu_conv(conv: nn.Module, negative_slope: float = 0.0) -> None:
    """Kaiming-normal (fan-in) for a conv followed by (leaky) ReLU; zero bias."""
    nn.init.kaiming_normal_(conv.weight, a=negative_slope, mode='fan_in', nonlinearity='leaky_relu')
    if conv.bias is not None:
        nn.init.zeros_(conv.bias)


def _init_linear_conv(conv: nn.Module, scale: float = 1.0) -> None:
    """Kaiming-normal with linear gain, times ``scale``; zero bias."""
    nn.init.kaiming_normal_(conv.weight, mode='fan_in', nonlinearity='linear')
    with torch.no_grad():
        conv.weight.mul_(scale)
    if conv.bias is not None:
        nn.init.zeros_(conv.bias)


class ResBlock2d(nn.Module):
    """PSM-Net BasicBlock without BN: ``x + conv_b(relu(conv_a(x)))`` (no ReLU after the sum)."""

    def __init__(self, channels: int, dilation: int = 1, blocks_in_stage: int = 1):
        super().__init__()
        self.conv_a = _conv3x3(channels, channels, dilation=dilation)
        self.conv_b = _conv3x3(channels, channels, dilation=dilation)
        _init_relu_conv(self.conv_a)
        _init_linear_conv(self.conv_b, 1.0 / math.sqrt(max(blocks_in_stage, 1)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.conv_b(F.relu(self.conv_a(x)))


def _stage(channels: int, blocks: int, dilation: int = 1) -> nn.Sequential:
    return nn.Sequential(*[ResBlock2d(channels, dilation, blocks) for _ in range(blocks)])


class ConvReLU(nn.Sequential):
    """A conv followed by ReLU (named submodule ``conv`` so parameter names read ``conv0_1.conv.weight``)."""

    def __init__(self, cin: int, cout: int, kernel: int = 3, stride: int = 1):
        super().__init__()
        self.conv = nn.Conv2d(cin, cout, kernel, stride=stride, padding=kernel // 2, bias=True)
        self.relu = nn.ReLU(inplace=True)
        _init_relu_conv(self.conv)


class SPPBranch(nn.Module):
    """avg_pool(size, stride=size) -> 1x1 conv -> ReLU -> bilinear back to the input size.

    The window is clamped per axis to the map size, so maps smaller than ``size`` give a global
    average on that axis instead of an error.
    """

    def __init__(self, cin: int, cout: int, pool_size: int):
        super().__init__()
        self.pool_size = int(pool_size)
        self.conv = nn.Conv2d(cin, cout, 1, bias=True)
        _init_relu_conv(self.conv)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2:]
        kh, kw = min(self.pool_size, h), min(self.pool_size, w)
        y = F.avg_pool2d(x, (kh, kw), stride=(kh, kw))
        y = F.relu(self.conv(y))
        return F.interpolate(y, size=(h, w), mode='bilinear', align_corners=False)


class FeatureExtractor(nn.Module):
    """PSM-Net feature extractor f(.) of the appendix table; input ImageNet-normalised RGB.

    ``forward(x_b3hw) -> ImageFeatures(fusion, half)``.
    """

    def __init__(self, preset: Preset):
        super().__init__()
        p = preset
        c0, c2, c3 = p.stem_channels, p.conv2_channels, p.conv3_channels
        self.conv0_1 = ConvReLU(3, c0, 3, stride=2)
        self.conv0_2 = ConvReLU(c0, c0)
        self.conv0_3 = ConvReLU(c0, c0)
        self.conv1 = _stage(c0, p.conv1_blocks)
        self.conv1_1 = ConvReLU(c0, c2, 3, stride=2)
        self.conv2 = _stage(c2, p.conv2_blocks)
        self.conv2_1 = ConvReLU(c2, c3)
        self.conv3 = _stage(c3, p.conv3_blocks)
        self.conv4 = _stage(c3, p.conv4_blocks, dilation=p.conv4_dilation)
        self.branches = nn.ModuleList([SPPBranch(c3, p.spp_channels, s) for s in p.spp_pool_sizes])
        concat = len(p.spp_pool_sizes) * p.spp_channels + c2 + c3
        self.concat_channels = concat
        self.fusion = nn.Sequential(ConvReLU(concat, p.fusion_channels, 3),
                                    ConvReLU(p.fusion_channels, p.feature_channels, 1))
        self.channels_last = False

    def forward(self, x_b3hw: torch.Tensor) -> ImageFeatures:
        if self.channels_last:
            x_b3hw = x_b3hw.contiguous(memory_format=torch.channels_last)
        x = self.conv0_3(self.conv0_2(self.conv0_1(x_b3hw)))
        half = self.conv1(x)
        x = self.conv1_1(half)
        out2 = self.conv2(x)
        x = self.conv3(self.conv2_1(out2))
        out4 = self.conv4(x)
        # table order: concat(branch1, branch2, branch3, branch4, conv2, conv4)
        cat = torch.cat([b(out4) for b in self.branches] + [out2, out4], dim=1)
        return ImageFeatures(self.fusion(cat), half)


class L1Cost(torch.autograd.Function):
    """``|warped - ref|`` summed over channels (dim 1), with ``ref`` (BN, C, 1, h, w) broadcast over the
    planes of ``warped`` (BN, C, d, h, w) -> (BN, d, h, w).

    Same values and gradients as ``(warped - ref).abs().sum(1)`` under autograd, but the backward pass
    keeps only the int8 sign of the difference and needs one multiply, where autograd's chain (sum ->
    abs -> sub with broadcasting) allocates and sweeps three more volume-sized tensors: on the CPU that
    was a tenth of a lite training step.
    """

    @staticmethod
    def forward(ctx, warped, ref):  # type: ignore[override]
        diff = warped - ref
        ctx.save_for_backward(torch.sign(diff).to(torch.int8))
        ctx.ref_shape = ref.shape
        return diff.abs_().sum(dim=1)

    @staticmethod
    def backward(ctx, grad_bdhw):  # type: ignore[override]
        (sign,) = ctx.saved_tensors
        grad_warped = grad_bdhw[:, None] * sign
        grad_ref = None
        if ctx.needs_input_grad[1]:
            grad_ref = -grad_warped.sum_to_size(ctx.ref_shape)
        return grad_warped, grad_ref


class CostVolume(nn.Module):
    """Plane-sweep L1 cost over the source views -> log-DPV (see the module docstring).

    The only parameter is the softmax temperature ``log_scale`` (``s = exp(log_scale)``).
    """

    def __init__(self, preset: Preset):
        super().__init__()
        self.log_scale = nn.Parameter(torch.tensor(math.log(preset.softmax_scale_init)))
        self.plane_chunk = int(preset.cost_plane_chunk)

    @property
    def scale(self) -> torch.Tensor:
        return self.log_scale.exp()

    def cost(self, ref_bchw: torch.Tensor, srcs_bnchw: torch.Tensor, K_vol_b33: torch.Tensor,
             T_src_ref_bn44: torch.Tensor, depths_d: torch.Tensor):
        """Per-voxel matching cost averaged over valid views.

        Returns ``cost_bdhw`` (neutral-filled where no view sees the voxel) and ``nvalid_bdhw`` (number
        of views seeing each voxel). Always computed in float32 with autocast disabled: pixel
        coordinates in half precision would be off by whole pixels.
        """
        B, C, h, w = ref_bchw.shape
        N = srcs_bnchw.shape[1]
        if srcs_bnchw.shape[0] != B or srcs_bnchw.shape[2:] != (C, h, w):
            raise ValueError(f'source features {tuple(srcs_bnchw.shape)} do not match reference '
                             f'{tuple(ref_bchw.shape)}')
        if T_src_ref_bn44.shape[:2] != (B, N):
            raise ValueError(f'T_src_ref {tuple(T_src_ref_bn44.shape)} does not match {N} source views, batch {B}')
        dt = torch.float32 if ref_bchw.dtype in (torch.float16, torch.bfloat16) else ref_bchw.dtype
        with no_autocast(ref_bchw.device):
            ref = ref_bchw.to(dt)
            # NHWC sources: grid_sample gathers all channels of a texel at once (~2x faster on the CPU)
            src = srcs_bnchw.to(dt).reshape(B * N, C, h, w).contiguous(memory_format=torch.channels_last)
            K = K_vol_b33.to(dt)
            K_bn = K[:, None].expand(B, N, 3, 3).reshape(B * N, 3, 3)
            T_bn = T_src_ref_bn44.to(dt).reshape(B * N, 4, 4)
            ref_bn = ref[:, None].expand(B, N, C, h, w).reshape(B * N, C, 1, h, w)
            depths = torch.as_tensor(depths_d, dtype=dt, device=ref.device)
            D = depths.shape[-1]
            costs, counts = [], []
            for d0 in range(0, D, self.plane_chunk):
                dd = depths[d0:d0 + self.plane_chunk]
                warped, valid = geometry.plane_sweep_warp(src, K_bn, K_bn, T_bn, dd, ref_hw=(h, w))
                if warped.requires_grad or ref_bn.requires_grad:
                    c = L1Cost.apply(warped, ref_bn)                           # BN, d, h, w
                else:                                                        # inference: no temporaries
                    c = warped.sub_(ref_bn).abs_().sum(dim=1)
                c = c * (1.0 / C)
                v = valid.to(dt)
                costs.append((c * v).reshape(B, N, -1, h, w).sum(1))
                counts.append(v.reshape(B, N, -1, h, w).sum(1))
            cost_sum = torch.cat(costs, 1)
            nvalid = torch.cat(counts, 1)
            seen = nvalid > 0
            cost = cost_sum / nvalid.clamp_min(1.0)
            # neutral fill: mean cost over the pixel's seen planes (0 when it has none -> uniform)
            seen_f = seen.to(dt)
            mean_seen = (cost * seen_f).sum(1, keepdim=True) / seen_f.sum(1, keepdim=True).clamp_min(1.0)
            cost = torch.where(seen, cost, mean_seen.expand_as(cost))
        return cost, nvalid

    def forward(self, ref_bchw, srcs_bnchw, K_vol_b33, T_src_ref_bn44, depths_d, return_cost: bool = False):
        """log-DPV ``log_softmax(-s * cost)`` (B, D, h, w), float32 (float64 for float64 inputs)."""
        cost, nvalid = self.cost(ref_bchw, srcs_bnchw, K_vol_b33, T_src_ref_bn44, depths_d)
        with no_autocast(cost.device):
            logp = normalize_log(-self.scale.to(cost.dtype) * cost)
        return (logp, cost, nvalid) if return_cost else logp


def stack_source_features(src_features: Sequence) -> torch.Tensor:
    """(B, N, C, h, w) fusion features from a sequence of N :class:`ImageFeatures` / (B, C, h, w) tensors."""
    fs = [f.fusion if isinstance(f, ImageFeatures) else f for f in src_features]
    if len(fs) == 0:
        raise ValueError('need at least one source view')
    return torch.stack(fs, dim=1)
