"""DPVNet: D-Net, K-Net and R-Net of one preset, with the interfaces the estimator and filter use.

    net = DPVNet('lite')
    logp_q, K_vol, feats = net.measure(ref_b3hw, srcs_bn3hw, K_b33, T_src_ref_bn44)   # D-Net
    correction = net.knet(residual_bdhw, image_b3hw)                                 # K-Net (DPVFilter)
    logp_full = net.refine(logp_q, feats, ref_b3hw)                                   # R-Net

Images are float RGB in [0, 1] (B, 3, H, W), normalised inside. ``K_b33`` is the full-resolution
intrinsics shared by the reference and source images; ``T_src_ref_bn44`` maps reference-camera points
into source view n. ``logp_q`` is (B, D, ceil(H/4), ceil(W/4)) and ``K_vol`` its intrinsics (see
``dnet.feature_intrinsics``). For streaming, ``extract_features(img)`` gives a frame's features once and
``measure(..., src_features=[...])`` reuses them (only the reference image is then run through the
extractor; pass ``ref_features`` too to skip even that).

Precision: float32, or under ``torch.autocast('cuda', dtype=torch.bfloat16)`` (or float16) on CUDA, or
``torch.autocast('cpu', dtype=torch.bfloat16)`` on a CPU where :func:`cpu_bf16_fast` (oneDNN's AMX /
AVX512-BF16 kernels: K-Net and the extractor 2x, a keyframe 1.25-1.4x faster there, emulated and slower
elsewhere) - the cost volume (pixel coordinates) and all log-softmaxes stay in float32 and every
returned DPV is float32. ``channels_last`` (default: on; on the CPU PyTorch's oneDNN convs are 2-4x
faster in NHWC) applies to the 2-D nets, ``channels_last_3d`` (default: on) to K-Net's 3-D convs: on the
CPU their backward pass is 2.7x faster in NDHWC while the forward pass costs about the same (a lite
training step at 256x192 takes 3.4 s instead of 4.9 s; inference in ``benchmarks.nets`` is unchanged), with
identical results.

Also here: :func:`count_parameters` and :func:`count_macs` (per stage, MACs counted with forward hooks
on the conv / transposed conv / linear layers; the cost volume's sampling and L1 are counted
analytically, see :func:`count_macs`).
"""
from __future__ import annotations

import functools
from collections import OrderedDict
from typing import Dict, Optional, Sequence, Union

import torch
import torch.nn as nn

from dpv_sensor.core.dpv import depth_planes
from dpv_sensor.core.nets.dnet import (CostVolume, FeatureExtractor, ImageFeatures, feature_intrinsics, normalize_image,
                   stack_source_features)
from dpv_sensor.core.nets.knet import KNet
from dpv_sensor.core.nets.presets import Preset, get_preset
from dpv_sensor.core.nets.rnet import RNet

__all__ = ['DPVNet', 'count_parameters', 'count_macs', 'STAGES', 'cpu_bf16_fast']

STAGES = ('feature_extraction', 'cost_volume', 'knet', 'rnet')


class DPVNet(nn.Module):
    """The three networks of one :class:`Preset` (see the module docstring).

    Submodules: ``features`` (PSM-Net extractor), ``cost_volume`` (softmax temperature), ``knet``,
    ``rnet``. ``depths_d`` is a non-persistent buffer with the D plane depths.
    """

    def __init__(self, preset: Union[str, Preset] = 'lite', channels_last: Optional[bool] = None,
                 channels_last_3d: Optional[bool] = None):
        super().__init__()
        self.preset = get_preset(preset)
        p = self.preset
        self.features = FeatureExtractor(p)
        self.cost_volume = CostVolume(p)
        self.knet = KNet(p)
        self.rnet = RNet(p)
        self.register_buffer('depths_d', depth_planes(p.d_min, p.d_max, p.num_planes), persistent=False)
        self._channels_last = False
        self.set_channels_last(channels_last if channels_last is not None else True,
                               channels_last_3d if channels_last_3d is not None else True)

    # ------------------------------------------------------------------ properties / layout
    @property
    def num_planes(self) -> int:
        return self.preset.num_planes

    @property
    def d_min(self) -> float:
        return self.preset.d_min

    @property
    def d_max(self) -> float:
        return self.preset.d_max

    def set_channels_last(self, enabled: bool = True, enabled_3d: bool = True) -> 'DPVNet':
        """Use NHWC memory layout in the 2-D nets (and NDHWC in K-Net if ``enabled_3d``)."""
        fmt = torch.channels_last if enabled else torch.contiguous_format
        for m in (self.features, self.rnet):
            m.to(memory_format=fmt)
            m.channels_last = bool(enabled)
        self.knet.channels_last = bool(enabled_3d)
        for m in self.knet.modules():
            if isinstance(m, nn.Conv3d) and m is not self.knet.conv0_a:
                m.weight.data = m.weight.data.contiguous(
                    memory_format=torch.channels_last_3d if enabled_3d else torch.contiguous_format)
        self._channels_last = bool(enabled)
        return self

    def depth_planes(self, dtype=torch.float32, device=None) -> torch.Tensor:
        return depth_planes(self.d_min, self.d_max, self.num_planes, dtype=dtype, device=device)

    # ------------------------------------------------------------------ D-Net
    def extract_features(self, image_b3hw: torch.Tensor) -> ImageFeatures:
        """Feature extractor on RGB in [0, 1] -> ImageFeatures(fusion 1/4, half 1/2). Cacheable per frame."""
        if image_b3hw.dim() != 4 or image_b3hw.shape[1] != 3:
            raise ValueError(f'expected an image batch (B, 3, H, W), got {tuple(image_b3hw.shape)}')
        return self.features(normalize_image(image_b3hw))

    @staticmethod
    def volume_intrinsics(K_b33: torch.Tensor) -> torch.Tensor:
        """Intrinsics of the quarter-resolution DPV grid for full-resolution ``K_b33``."""
        return feature_intrinsics(K_b33)

    def measure(self, ref_b3hw: torch.Tensor, srcs_bn3hw: Optional[torch.Tensor], K_b33: torch.Tensor,
                T_src_ref_bn44: torch.Tensor, src_features: Optional[Sequence] = None,
                ref_features: Optional[ImageFeatures] = None):
        """D-Net: the measurement DPV of the reference frame.

        Args:
            ref_b3hw: (B, 3, H, W) reference image, RGB in [0, 1].
            srcs_bn3hw: (B, N, 3, H, W) source images (may be None when ``src_features`` is given).
            K_b33: (B, 3, 3) full-resolution intrinsics (shared by all images).
            T_src_ref_bn44: (B, N, 4, 4) reference-camera -> source-camera transforms.
            src_features: cached features of the N sources: a sequence of N ``ImageFeatures`` (or
                (B, C, h, w) fusion tensors), or a (B, N, C, h, w) tensor.
            ref_features: cached features of the reference image.
        Returns:
            (logp_bdhw quarter-res float32, K_vol_b33, feats: ImageFeatures of the reference for R-Net)
        """
        feats = ref_features if ref_features is not None else self.extract_features(ref_b3hw)
        if src_features is None:
            if srcs_bn3hw is None:
                raise ValueError('need source images or cached source features')
            B, N = srcs_bn3hw.shape[:2]
            if srcs_bn3hw.shape[2:] != ref_b3hw.shape[1:]:
                raise ValueError(f'source images {tuple(srcs_bn3hw.shape)} do not match the reference '
                                 f'{tuple(ref_b3hw.shape)}')
            f = self.extract_features(srcs_bn3hw.reshape(B * N, *srcs_bn3hw.shape[2:])).fusion
            src = f.reshape(B, N, *f.shape[1:])
        elif torch.is_tensor(src_features):
            src = src_features
        else:
            src = stack_source_features(src_features)
        K_vol = self.volume_intrinsics(K_b33)
        depths = self.depths_d.to(device=feats.fusion.device)
        if feats.fusion.dtype == torch.float64:
            depths = self.depth_planes(torch.float64, feats.fusion.device)
        logp = self.cost_volume(feats.fusion, src, K_vol, T_src_ref_bn44, depths)
        return logp, K_vol, feats

    # ------------------------------------------------------------------ R-Net
    def refine(self, logp_quarter_bdhw: torch.Tensor, feats: ImageFeatures, ref_b3hw: torch.Tensor) -> torch.Tensor:
        """R-Net: quarter-resolution log-DPV -> full-resolution log-DPV (B, D, H, W)."""
        return self.rnet(logp_quarter_bdhw, feats.fusion, feats.half, normalize_image(ref_b3hw))

    def forward(self, ref_b3hw, srcs_bn3hw, K_b33, T_src_ref_bn44):
        """D-Net then R-Net (no temporal filtering): full-resolution log-DPV."""
        logp, _, feats = self.measure(ref_b3hw, srcs_bn3hw, K_b33, T_src_ref_bn44)
        return self.refine(logp, feats, ref_b3hw)


# ---------------------------------------------------------------------- precision
@functools.lru_cache(maxsize=None)
@functools.lru_cache(maxsize=1)
def _cpu_flags_line() -> Optional[str]:
    """The ``flags`` line of ``/proc/cpuinfo`` (read once), or None where there is none."""
    try:
        with open('/proc/cpuinfo') as f:
            return next((line for line in f if line.startswith('flags')), None)
    except OSError:
        return None


def cpu_bf16_fast(cpu_flags: Optional[str] = None) -> bool:
    """True when this CPU has native bfloat16 arithmetic (AVX512-BF16 or AMX), i.e. when CPU autocast to
    bfloat16 is faster than float32 rather than emulated.

    oneDNN's own answer (``torch.ops.mkldnn._is_mkldnn_bf16_supported``) is True on every AVX-512 CPU, where
    bfloat16 runs converted to float32 and back: there a keyframe took 400 ms against 240 ms in float32. So on
    Linux the CPU's flags decide (``/proc/cpuinfo``, or ``cpu_flags``, its ``flags`` line, for a test); oneDNN's
    answer is used only where the flags cannot be read."""
    if cpu_flags is None:
        cpu_flags = _cpu_flags_line()
    if cpu_flags is not None:
        return bool({'avx512_bf16', 'amx_bf16'} & set(cpu_flags.split(':', 1)[-1].split()))
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False


# ---------------------------------------------------------------------- counting
def count_parameters(model: DPVNet) -> Dict[str, int]:
    """Trainable parameters per stage (feature_extraction, cost_volume, knet, rnet) and 'total'."""
    out = OrderedDict()
    for stage, m in zip(STAGES, (model.features, model.cost_volume, model.knet, model.rnet)):
        out[stage] = sum(p.numel() for p in m.parameters())
    out['total'] = sum(p.numel() for p in model.parameters())
    return out


def _layer_macs(module: nn.Module, inputs, output) -> int:
    """Multiply-accumulates of one forward call of a conv / transposed conv / linear layer."""
    if hasattr(module, 'mac_count'):                    # layers that compute their own (K-Net conv_0)
        return int(module.mac_count)
    if isinstance(module, (nn.ConvTranspose1d, nn.ConvTranspose2d, nn.ConvTranspose3d)):
        x = inputs[0]
        k = 1
        for s in module.kernel_size:
            k *= s
        return x.numel() * (module.out_channels // module.groups) * k
    if isinstance(module, (nn.Conv1d, nn.Conv2d, nn.Conv3d)):
        k = 1
        for s in module.kernel_size:
            k *= s
        return output.numel() * (module.in_channels // module.groups) * k
    if isinstance(module, nn.Linear):
        return output.numel() * module.in_features
    return 0


class _MacCounter:
    """Context manager: forward hooks on every conv / transposed conv / linear layer of ``module``."""

    LAYERS = (nn.Conv1d, nn.Conv2d, nn.Conv3d, nn.ConvTranspose1d, nn.ConvTranspose2d, nn.ConvTranspose3d,
              nn.Linear)

    def __init__(self, module: nn.Module):
        self.module = module
        self.macs = 0
        self.handles = []

    def _hook(self, module, inputs, output):
        self.macs += _layer_macs(module, inputs, output)

    def __enter__(self):
        for m in self.module.modules():
            if isinstance(m, self.LAYERS):
                self.handles.append(m.register_forward_hook(self._hook))
        return self

    def __exit__(self, *exc):
        for h in self.handles:
            h.remove()
        self.handles = []
        return False


def cost_volume_macs(B: int, N: int, C: int, D: int, h: int, w: int) -> int:
    """Analytic count for the cost volume: per view and voxel, bilinear sampling of C channels
    (4 MACs each) plus the L1 difference (1 MAC per channel) -> 5*C*N*D*h*w."""
    return 5 * C * N * D * h * w * B


@torch.no_grad()
def count_macs(model: DPVNet, height: int, width: int, num_sources: int = 4) -> Dict[str, int]:
    """Multiply-accumulates per stage for one keyframe of size height x width (batch 1).

    ``feature_extraction`` is for ONE image (a streaming estimator extracts each frame once; a cold
    window needs 1 + num_sources of them, reported as ``feature_extraction_window``); ``cost_volume``
    is analytic (:func:`cost_volume_macs`); ``knet`` and ``rnet`` are counted with forward hooks.
    ``total_streaming`` = one extraction + cost volume + K-Net + R-Net; ``total_window`` uses
    1 + num_sources extractions. Runs the nets once on random input (CPU, float32).
    """
    p = model.preset
    dev = next(model.parameters()).device
    img = torch.rand(1, 3, height, width, device=dev)
    out = OrderedDict()
    with _MacCounter(model.features) as c:
        feats = model.extract_features(img)
    out['feature_extraction'] = c.macs
    _, _, h, w = feats.fusion.shape
    out['cost_volume'] = cost_volume_macs(1, num_sources, p.feature_channels, p.num_planes, h, w)
    residual = torch.randn(1, p.num_planes, h, w, device=dev)
    with _MacCounter(model.knet) as c:
        model.knet(residual, img)
    out['knet'] = c.macs
    logp = torch.log_softmax(torch.randn(1, p.num_planes, h, w, device=dev), 1)
    with _MacCounter(model.rnet) as c:
        model.refine(logp, feats, img)
    out['rnet'] = c.macs
    out['feature_extraction_window'] = out['feature_extraction'] * (1 + num_sources)
    rest = out['cost_volume'] + out['knet'] + out['rnet']
    out['total_streaming'] = out['feature_extraction'] + rest
    out['total_window'] = out['feature_extraction_window'] + rest
    return out
