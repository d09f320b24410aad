"""K-Net: adaptive damping of the DPV filter update (paper Sec. 3.2, eqs. 9-10).

The filter (``DPVFilter(mode='knet', knet=...)``) works on energies ``E = -log p`` and updates

    E(d_t+1 | I_1:t+1) = E_pred + g(dE, I_t+1),      dE = E_meas - E_pred        (eqs. 9, 10)

``KNet.forward(residual_bdhw, image_b3hw)`` is ``g``. Its layers are the appendix table "K-Net
structure" (channel counts of the ``paper`` preset; ``lite`` changes width and block count):

    input   concat(residual, expand(I_ref))        D x h x w x 4   (1 residual + 3 RGB channels)
    conv_0  conv3d 3x3x3 4->32, ReLU; conv3d 32->32, ReLU
    conv_1  4 x [conv3d 32->32, ReLU, conv3d 32->32] + skip
    conv_2  conv3d 32->32, ReLU; conv3d 32->1       -> the correction (D x h x w)

Every conv3d has a bias (no BN); residual blocks are ``x + conv(relu(conv(x)))``, as in the D-Net.
The image is ImageNet-normalised and brought to the volume's resolution inside (a 5x5 box average
with stride 4 centred on full-resolution pixel 4j, i.e. exactly on the volume grid of
``dnet.feature_intrinsics``, when the image is 4x the volume; an adaptive average otherwise).

Initialisation: close to global damping. Besides the table's layers K-Net has one scalar, the gain
``k`` of an identity path: ``g = k * dE + conv_2(...)``. ``conv_2``'s last layer starts at zero, so at
step 0 ``g = k dE`` and the update is ``E = (1 - k) E_pred + k E_meas``, a Kalman-style blend.
``k`` starts at ``1 / (1 + lambda)`` (lambda = ``preset.knet_damping_init``, 0.8 as in the paper):
the blend then weights prediction and measurement exactly as global damping
``lambda E_pred + E_meas`` does (eq. 8) - the two differ only by the overall factor ``1 + lambda``
(global damping's posterior is sharper by that factor; a correction that sees only ``dE`` cannot
reproduce a multiple of ``E_pred``). Training then learns where to deviate from it.

The first conv3d (4 input channels) is computed exactly but cheaply: the three image channels are
constant along depth, so their 3x3x3 contribution is one 2-D conv of the image with the kernel summed
over the depth taps (minus the missing tap at the first and last plane); the residual channel's part
is a 2-D conv over the three depth-shifted copies of the residual. PyTorch's CPU conv3d with fewer than
about 12 input channels is ~30x slower per MAC than with 32, which made this layer alone cost more
than the rest of K-Net. Parameters and results are those of a plain ``nn.Conv3d(4, C, 3, padding=1)``.

The other 3-D convs (:class:`VolumeConv3d`) call oneDNN directly on the CPU in float32. PyTorch chooses
between oneDNN and its unfold-and-multiply fallback by a size rule written for images: with one sample it
takes oneDNN only when batch x channels x the first two spatial sizes exceed 20480, which for a volume is
channels x D x h and leaves the width out. A ``lite`` volume of 32 planes at 40x32 (a 160x128 image) is
under it, and there the fallback was 11x slower per conv (68 against 6 ms, one thread); at 320x256 the
rule already picks oneDNN and the results are the same bit for bit. The backward of one sample (adaptation,
training on single keyframes) is computed from oneDNN convs too, 5x faster at 160x128. The last layer (C -> 1) is
:class:`PlanewiseConv3d`: oneDNN's 3-D conv with one output channel costs as much as one with C.
"""
from __future__ import annotations

import math

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch.autograd.function import once_differentiable

from dpv_sensor.core.nets.dnet import FEATURE_STRIDE, normalize_image
from dpv_sensor.core.nets.presets import Preset

__all__ = ['KNet', 'ExpandedInputConv3d', 'VolumeConv3d', 'PlanewiseConv3d', 'depth_halves', 'ResBlock3d',
           'image_to_volume_grid']

# Residual energies beyond this magnitude (nats) are clipped at the conv branch's input only
# (the identity path sees the true residual). Keeps -log(0)-style outliers from saturating the net.
RESIDUAL_CLIP = 100.0


def image_to_volume_grid(image_b3hw: torch.Tensor, hw) -> torch.Tensor:
    """Downsample an image to the volume grid (h, w).

    If the image is (about) 4x the volume (``ceil(H/4) == h``), a 5x5 box filter with stride 4 and
    padding 2 is used: output pixel j averages full-resolution pixels 4j-2..4j+2, i.e. it is centred on
    4j like the feature grid. Equal sizes pass through; other sizes use an adaptive average.
    """
    H, W = image_b3hw.shape[-2:]
    h, w = int(hw[0]), int(hw[1])
    if (H, W) == (h, w):
        return image_b3hw
    if -(-H // FEATURE_STRIDE) == h and -(-W // FEATURE_STRIDE) == w:
        return F.avg_pool2d(image_b3hw, 5, stride=FEATURE_STRIDE, padding=2, count_include_pad=False)
    return F.adaptive_avg_pool2d(image_b3hw, (h, w))


def _exporting() -> bool:
    """Whether the module is being traced, scripted, exported or compiled: then only ordinary ops may run."""
    return (torch.jit.is_tracing() or torch.jit.is_scripting() or torch.onnx.is_in_onnx_export()
            or torch.compiler.is_compiling())


def _onednn_fits(input: torch.Tensor, weight: torch.Tensor) -> bool:
    """Whether a float32 CPU conv may go to oneDNN directly: not under autocast (which casts the conv's inputs
    itself), not while exporting or compiling."""
    return (input.device.type == 'cpu' and input.dtype == torch.float32 and weight.dtype == torch.float32
            and torch.backends.mkldnn.is_available() and torch.backends.mkldnn.enabled
            and not torch.is_autocast_enabled('cpu') and not _exporting())


def depth_halves(input_bcdhw: torch.Tensor, grad_bodhw: torch.Tensor, pad_d: int):
    """A one-sample stride-1 3-D conv's (input, output gradient) as a batch of two: the output planes split into
    two halves (an odd count gets a zero plane at the end), each half with the input planes it reads (its halo of
    ``pad_d`` planes each side, zeros beyond the volume). The weight and bias gradients of the pair, with depth
    padding 0, are those of the one sample; PyTorch's size rule sends a batch of two to oneDNN."""
    D = grad_bodhw.shape[2]
    n = -(-D // 2)
    x = F.pad(input_bcdhw, (0, 0, 0, 0, pad_d, pad_d + 2 * n - D))
    g = F.pad(grad_bodhw, (0, 0, 0, 0, 0, 2 * n - D))
    return (torch.cat([x[:, :, :n + 2 * pad_d], x[:, :, n:]]), torch.cat([g[:, :, :n], g[:, :, n:]]))


class _OneDnnSameConv3d(torch.autograd.Function):
    """A one-sample float32 3-D conv with stride 1, no dilation, one group and 'same' padding (``2 p = k - 1``)
    on oneDNN forward and backward. The input gradient is the forward conv of the output gradient with the
    kernel transposed and flipped; the weight and bias gradients come from :func:`depth_halves`. PyTorch's own
    backward of this shape runs its fallback: 113 against 20 ms for K-Net's 12-channel conv on a 160x128 image's
    volume, one thread."""

    @staticmethod
    def forward(ctx, input, weight, bias, padding):
        ctx.save_for_backward(input, weight)
        ctx.padding, ctx.has_bias = padding, bias is not None
        return torch.mkldnn_convolution(input, weight, bias, padding, [1, 1, 1], [1, 1, 1], 1)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out):
        input, weight = ctx.saved_tensors
        grad_input = grad_weight = grad_bias = None
        grad_out = grad_out.contiguous()
        if ctx.needs_input_grad[0]:
            flipped = weight.transpose(0, 1).flip(2, 3, 4).contiguous()
            grad_input = torch.mkldnn_convolution(grad_out, flipped, None, ctx.padding, [1, 1, 1], [1, 1, 1], 1)
        if ctx.needs_input_grad[1] or ctx.needs_input_grad[2]:
            xs, gs = depth_halves(input, grad_out, ctx.padding[0])
            _, grad_weight, grad_bias = torch.ops.aten.convolution_backward(
                gs, xs, weight, [weight.shape[0]] if ctx.has_bias else None, [1, 1, 1], [0, *ctx.padding[1:]],
                [1, 1, 1], False, [0, 0, 0], 1, [False, True, ctx.has_bias])
        return grad_input, grad_weight, grad_bias, None


class VolumeConv3d(nn.Conv3d):
    """``nn.Conv3d`` whose float32 CPU forward always runs oneDNN (see the module docstring), and for one sample
    with 'same' padding its backward too (:class:`_OneDnnSameConv3d`). Elsewhere (a GPU, autocast, export) it is
    ``nn.Conv3d`` unchanged."""

    def _conv_forward(self, input: torch.Tensor, weight: torch.Tensor, bias):  # type: ignore[override]
        if self.padding_mode == 'zeros' and not isinstance(self.padding, str) and _onednn_fits(input, weight):
            padding = list(self.padding)
            if (torch.is_grad_enabled() and (input.requires_grad or weight.requires_grad) and input.shape[0] == 1
                    and self.groups == 1 and self.stride == (1, 1, 1) and self.dilation == (1, 1, 1)
                    and all(2 * p == k - 1 for p, k in zip(padding, self.kernel_size))):
                return _OneDnnSameConv3d.apply(input, weight, bias, padding)
            return torch.mkldnn_convolution(input, weight, bias, padding, list(self.stride),
                                            list(self.dilation), self.groups)
        return super()._conv_forward(input, weight, bias)


class PlanewiseConv3d(VolumeConv3d):
    """``nn.Conv3d(C, 1, 3, padding=1)`` (K-Net's last layer) computed as one 2-D conv over the depth planes: the
    planes as a batch, C channels in, one output per depth tap; the taps' maps summed shifted along depth (tap
    ``kd`` of plane ``d`` lands on output plane ``d + 1 - kd``) in float32 or wider. oneDNN's 3-D conv with a
    single output channel costs as much as one with twelve (21 ms against 8 for this form at 320x256, one
    thread). Parameters and results are those of the plain conv; on a GPU it is the plain conv."""

    def __init__(self, in_channels: int, out_channels: int = 1, kernel_size=3, padding=1):
        super().__init__(in_channels, out_channels, kernel_size, padding=padding)
        if (self.out_channels, self.kernel_size, self.padding) != (1, (3, 3, 3), (1, 1, 1)):
            raise ValueError(f'PlanewiseConv3d is a C -> 1 conv with a 3x3x3 kernel and padding 1, got '
                             f'{self.out_channels} outputs, kernel {self.kernel_size}, padding {self.padding}')

    def _conv_forward(self, input: torch.Tensor, weight: torch.Tensor, bias):  # type: ignore[override]
        if input.device.type != 'cpu' or _exporting():
            return super()._conv_forward(input, weight, bias)
        B, C, D, h, w = input.shape
        planes = input.transpose(1, 2).reshape(B * D, C, h, w)
        taps = F.conv2d(planes, weight[0].transpose(0, 1), padding=1).reshape(B, D, 3, h, w)
        taps = taps.to(torch.promote_types(taps.dtype, torch.float32))     # the taps summed in float32 or wider
        out = taps[:, :, 1].clone()
        out[:, 1:] += taps[:, :-1, 0]
        out[:, :-1] += taps[:, 1:, 2]
        if bias is not None:
            out = out + bias.to(out.dtype)
        return out[:, None]


class ExpandedInputConv3d(nn.Conv3d):
    """``nn.Conv3d(1 + 3, C, 3, padding=1)`` applied to ``concat(volume, expand(image))``, computed
    as 2-D convolutions (see the module docstring). ``forward(volume_bdhw, image_b3hw)``."""

    def __init__(self, out_channels: int, image_channels: int = 3):
        super().__init__(1 + image_channels, out_channels, 3, padding=1, bias=True)
        self.image_channels = image_channels
        self.mac_count = 0

    def forward(self, volume_bdhw: torch.Tensor, image_bchw: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        B, D, h, w = volume_bdhw.shape
        C = self.out_channels
        Wt = self.weight                                       # C, 4, 3(kd), 3, 3
        vol, img = volume_bdhw, image_bchw.to(volume_bdhw.dtype)
        # residual channel: 3 depth-shifted copies -> 2-D conv with the (kd, kh, kw) kernel
        pad = F.pad(vol, (0, 0, 0, 0, 1, 1))                   # B, D+2, h, w (zeros at both ends)
        shifted = torch.stack([pad[:, 0:D], pad[:, 1:D + 1], pad[:, 2:D + 2]], dim=2)   # B, D, 3, h, w
        y = F.conv2d(shifted.reshape(B * D, 3, h, w), Wt[:, 0], padding=1)                        # B*D, C, h, w
        y = y.reshape(B, D, C, h, w).permute(0, 2, 1, 3, 4)                               # B, C, D, h, w
        # image channels: one 2-D conv per depth tap, summed; the end planes miss one tap each
        wi = Wt[:, 1:].permute(2, 0, 1, 3, 4).reshape(3 * C, self.image_channels, 3, 3)  # (kd, C), ci, 3, 3
        p = F.conv2d(img, wi, padding=1).reshape(B, 3, C, h, w)
        full = p.sum(1)
        img_term = full[:, :, None].expand(B, C, D, h, w)
        if D >= 2:
            first = (full - p[:, 0])[:, :, None]
            last = (full - p[:, 2])[:, :, None]
            mid = img_term[:, :, 1:D - 1]
            img_term = torch.cat([first, mid, last], dim=2)
        else:
            img_term = p[:, 1][:, :, None]
        out = y + img_term + self.bias.view(1, C, 1, 1, 1)
        self.mac_count = B * D * h * w * C * 27 + B * h * w * 3 * C * self.image_channels * 9
        return out


class ResBlock3d(nn.Module):
    """``x + conv_b(relu(conv_a(x)))`` with 3x3x3 convs (no BN, no ReLU after the sum)."""

    def __init__(self, channels: int, blocks_in_stage: int = 1):
        super().__init__()
        self.conv_a = VolumeConv3d(channels, channels, 3, padding=1)
        self.conv_b = VolumeConv3d(channels, channels, 3, padding=1)
        nn.init.kaiming_normal_(self.conv_a.weight, nonlinearity='relu')
        nn.init.zeros_(self.conv_a.bias)
        nn.init.kaiming_normal_(self.conv_b.weight, nonlinearity='linear')
        with torch.no_grad():
            self.conv_b.weight.mul_(1.0 / math.sqrt(max(blocks_in_stage, 1)))
        nn.init.zeros_(self.conv_b.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.conv_b(F.relu(self.conv_a(x)))


class KNet(nn.Module):
    """g(residual_bdhw, image_b3hw) -> correction_bdhw (see the module docstring).

    ``residual_bdhw`` = E_meas - E_pred on the quarter-resolution volume grid; ``image_b3hw`` = the new
    frame, RGB in [0, 1], at full resolution (or already at the volume's size).
    """

    def __init__(self, preset: Preset):
        super().__init__()
        C = preset.knet_channels
        self.conv0_a = ExpandedInputConv3d(C)
        self.conv0_b = VolumeConv3d(C, C, 3, padding=1)
        self.conv1 = nn.Sequential(*[ResBlock3d(C, preset.knet_blocks) for _ in range(preset.knet_blocks)])
        self.conv2_a = VolumeConv3d(C, C, 3, padding=1)
        self.conv2_b = PlanewiseConv3d(C, 1, 3, padding=1)
        for conv in (self.conv0_a, self.conv0_b, self.conv2_a):
            nn.init.kaiming_normal_(conv.weight, nonlinearity='relu')
            nn.init.zeros_(conv.bias)
        nn.init.zeros_(self.conv2_b.weight)     # step 0: g = gain * residual
        nn.init.zeros_(self.conv2_b.bias)
        lam = float(preset.knet_damping_init)
        self.gain = nn.Parameter(torch.tensor(1.0 / (1.0 + lam)))
        self.channels_last = False

    def forward(self, residual_bdhw: torch.Tensor, image_b3hw: torch.Tensor) -> torch.Tensor:
        B, D, h, w = residual_bdhw.shape
        if image_b3hw.shape[0] != B:
            raise ValueError(f'image batch {image_b3hw.shape[0]} != residual batch {B}')
        img = image_to_volume_grid(normalize_image(image_b3hw.to(residual_bdhw.dtype)), (h, w))
        r = residual_bdhw.clamp(-RESIDUAL_CLIP, RESIDUAL_CLIP)
        x = F.relu(self.conv0_a(r, img))
        if self.channels_last:
            x = x.contiguous(memory_format=torch.channels_last_3d)
        x = F.relu(self.conv0_b(x))
        x = self.conv1(x)
        x = self.conv2_b(F.relu(self.conv2_a(x)))[:, 0]
        # (under autocast x is half precision; the sum promotes back to the residual's float32)
        return self.gain * residual_bdhw + x
