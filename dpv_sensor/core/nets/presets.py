"""Network presets: ``paper`` (the appendix layer tables exactly) and ``lite`` (a 2-core CPU).

A :class:`Preset` fixes everything that changes the weights' shapes or the meaning of the DPV
(number of planes and their depth range), plus the nominal input size. ``get_preset(name)`` returns
the registered presets; a customised copy is made with ``dataclasses.replace(preset, ...)`` (a
checkpoint stores the full preset, so a custom one round-trips).

Depth range (both presets): 0.3 m .. 8.0 m, i.e. the indoor range of an RGB-D camera. On the
development data (the shared development data folder) the 0.1 % / 99.9 % GT depth percentiles are 0.97/4.3 m
(sun3d frag1), 1.34/6.5 m (sun3d frag2) and 0.18/14.5 m (tartanair hospital, 1 %/99 %: 0.24/7.3 m),
so 0.3..8 m covers > 98 % of the valid GT pixels while keeping the plane spacing (uniform in inverse
depth: 1/0.3 - 1/8 = 3.21 m^-1 over D-1 intervals) fine enough for near objects.

The ``paper`` preset reproduces the appendix (tables "D-Net structure", "K-Net structure",
"R-Net structure") with D = 64 planes. The ``lite`` preset keeps the same structure and interfaces
with thinner layers, fewer residual blocks and D = 32 planes, sized so that one keyframe at
320x256 with 4 source views (feature extraction, cost volume, K-Net, R-Net) runs well under 300 ms
on a 2-core x86 CPU (see ``python -m dpv_sensor.benchmarks.nets``). Measured on the development
machine (2 cores of an AMD EPYC Zen 4, torch 2.15, float32, 2 threads, load average 1.1):
206 ms median per keyframe with the source features cached (17 features + 42 cost volume + 83 K-Net
+ 57 R-Net), 230 ms when all 5 window images go through the extractor; 5.7 / 10.3 GMAC. ``paper``
at 320x256 needs 126 GMAC per keyframe (2.5 s on the same CPU; K-Net alone is 91 GMAC).

Note: ``feature_channels=16`` and the other ``lite`` widths are what the lite weights were trained
with; changing any field other than the runtime ones (``cost_plane_chunk``, the ``*_init`` values,
``input_size``, ``description``) makes existing lite checkpoints refuse to load.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Dict, Optional, Tuple

__all__ = ['Preset', 'PRESETS', 'get_preset', 'preset_names', 'preset_from_dict']


@dataclass(frozen=True)
class Preset:
    """Hyper-parameters of one D-Net / K-Net / R-Net configuration.

    Names in brackets refer to the appendix tables; the ``paper`` values are the tables' values.
    """
    name: str
    # --- depth probability volume -------------------------------------------------------------
    num_planes: int = 64                        # D, planes uniform in inverse depth
    d_min: float = 0.3                          # metres (plane index 0)
    d_max: float = 8.0                          # metres (plane index D-1)
    input_size: Tuple[int, int] = (640, 480)    # nominal (width, height) the nets are run/trained at
    # --- D-Net feature extractor (PSM-Net) -----------------------------------------------------
    stem_channels: int = 32                     # conv0_1..conv0_3 and conv1 (half resolution)
    conv1_blocks: int = 3                       # residual blocks in conv1
    conv2_channels: int = 64                    # conv1_1 (stride 2) and conv2 (quarter resolution)
    conv2_blocks: int = 15                      # residual blocks in conv2
    conv3_channels: int = 128                   # conv2_1, conv3, conv4
    conv3_blocks: int = 2                       # residual blocks in conv3
    conv4_blocks: int = 3                       # dilated residual blocks in conv4
    conv4_dilation: int = 2
    spp_channels: int = 32                      # channels of each SPP branch (1x1 conv)
    spp_pool_sizes: Tuple[int, ...] = (64, 32, 16, 8)   # avg-pool window/stride of branch1..4
    fusion_channels: int = 128                  # fusion 3x3 conv output
    feature_channels: int = 64                  # fusion 1x1 conv output = the D-Net feature
    # --- cost volume -> DPV --------------------------------------------------------------------
    softmax_scale_init: float = 10.0            # logits = -scale * cost (scale is learnt)
    cost_plane_chunk: int = 16                  # planes warped at once (bounds memory only)
    # --- K-Net ---------------------------------------------------------------------------------
    knet_channels: int = 32
    knet_blocks: int = 4                        # residual blocks in conv_1
    knet_damping_init: float = 0.8              # lambda of the global damping K-Net starts from
    # --- R-Net ---------------------------------------------------------------------------------
    rnet_up0_channels: Optional[int] = None     # trans_conv_0 output (None: D, as in the table)
    rnet_up1_channels: Optional[int] = None     # trans_conv_1 output (None: D, as in the table)
    leaky_slope: float = 0.1                    # LeakyReLU negative slope (the table gives none)
    # --- free text -------------------------------------------------------------------------------
    description: str = field(default='', compare=False)

    @property
    def D(self) -> int:
        """Alias of ``num_planes``."""
        return self.num_planes

    @property
    def up0_channels(self) -> int:
        return self.num_planes if self.rnet_up0_channels is None else self.rnet_up0_channels

    @property
    def up1_channels(self) -> int:
        return self.num_planes if self.rnet_up1_channels is None else self.rnet_up1_channels

    def validate(self) -> 'Preset':
        """Raise ValueError on inconsistent values; returns self."""
        if not (0.0 < self.d_min < self.d_max):
            raise ValueError(f'preset {self.name!r}: need 0 < d_min < d_max, got {self.d_min}, {self.d_max}')
        if self.num_planes < 2:
            raise ValueError(f'preset {self.name!r}: need at least 2 planes, got {self.num_planes}')
        if len(self.input_size) != 2 or min(self.input_size) < 8:
            raise ValueError(f'preset {self.name!r}: input_size must be (width, height) >= 8, got {self.input_size}')
        if len(self.spp_pool_sizes) == 0 or min(self.spp_pool_sizes) < 1:
            raise ValueError(f'preset {self.name!r}: spp_pool_sizes must be positive, got {self.spp_pool_sizes}')
        for f in ('stem_channels', 'conv2_channels', 'conv3_channels', 'spp_channels', 'fusion_channels',
                  'feature_channels', 'knet_channels', 'cost_plane_chunk', 'conv4_dilation'):
            if getattr(self, f) < 1:
                raise ValueError(f'preset {self.name!r}: {f} must be >= 1, got {getattr(self, f)}')
        for f in ('conv1_blocks', 'conv2_blocks', 'conv3_blocks', 'conv4_blocks', 'knet_blocks'):
            if getattr(self, f) < 0:
                raise ValueError(f'preset {self.name!r}: {f} must be >= 0, got {getattr(self, f)}')
        if not (0.0 <= self.knet_damping_init <= 1.0):
            raise ValueError(f'preset {self.name!r}: knet_damping_init must lie in [0, 1]')
        if self.softmax_scale_init <= 0:
            raise ValueError(f'preset {self.name!r}: softmax_scale_init must be > 0')
        return self

    def to_dict(self) -> Dict:
        """JSON-friendly dict (tuples become lists); inverse of :func:`preset_from_dict`."""
        d = dataclasses.asdict(self)
        d['input_size'] = list(self.input_size)
        d['spp_pool_sizes'] = list(self.spp_pool_sizes)
        return d


def preset_from_dict(d: Dict) -> Preset:
    """Rebuild a :class:`Preset` from :meth:`Preset.to_dict` output (unknown keys are an error)."""
    known = {f.name for f in dataclasses.fields(Preset)}
    unknown = sorted(set(d) - known)
    if unknown:
        raise ValueError(f'unknown preset fields {unknown}')
    kw = dict(d)
    if 'input_size' in kw:
        kw['input_size'] = tuple(int(v) for v in kw['input_size'])
    if 'spp_pool_sizes' in kw:
        kw['spp_pool_sizes'] = tuple(int(v) for v in kw['spp_pool_sizes'])
    return Preset(**kw).validate()


PAPER = Preset(
    name='paper',
    num_planes=64,
    input_size=(640, 480),
    description='Appendix tables of Liu et al. (CVPR 2019) exactly: PSM-Net feature extractor '
                '(3.14 M parameters), K-Net with 4 residual 3-D blocks of 32 channels, R-Net U-Net; D = 64.',
)

LITE = Preset(
    name='lite',
    num_planes=32,
    input_size=(320, 256),
    stem_channels=16,
    conv1_blocks=1,
    conv2_channels=32,
    conv2_blocks=2,
    conv3_channels=48,
    conv3_blocks=1,
    conv4_blocks=1,
    spp_channels=8,
    fusion_channels=48,
    feature_channels=16,
    cost_plane_chunk=8,
    knet_channels=12,
    knet_blocks=1,
    rnet_up0_channels=16,
    rnet_up1_channels=8,
    description='Same structure, thinner: for a 2-core CPU at 320x256 (D = 32).',
)

PRESETS: Dict[str, Preset] = {p.name: p.validate() for p in (PAPER, LITE)}


def preset_names() -> Tuple[str, ...]:
    return tuple(PRESETS)


def get_preset(name) -> Preset:
    """The registered preset ``name`` ('paper' or 'lite'); a :class:`Preset` is returned unchanged."""
    if isinstance(name, Preset):
        return name.validate()
    try:
        return PRESETS[str(name)]
    except KeyError:
        raise ValueError(f'unknown preset {name!r}; known presets: {", ".join(PRESETS)}') from None
