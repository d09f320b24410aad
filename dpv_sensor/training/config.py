"""The trainer's settings (:class:`TrainConfig`, stored in every checkpoint's state.json) and the validation
score that decides exports (:func:`parse_select_metric`, :func:`select_score`)."""
from __future__ import annotations

import dataclasses
import pathlib
from typing import Dict, NamedTuple, Optional, Tuple

import numpy as np

from dpv_sensor import params as _params
from dpv_sensor.training.dataset import (TRAIN_SEED_BASE, VAL_SEEDS, Augment, StreamConfig, WindowLayout,
                                         check_not_heldout)
from dpv_sensor.training.stream_validation import STREAM_PREFIX, StreamValidationSpec, stream_metric_key

__all__ = ['TrainConfig', 'SelectMetric', 'parse_select_metric', 'select_score', 'FILTER_MODES', 'MODULES']

FILTER_MODES = ('none', 'global', 'knet')
# the sub-networks of DPVNet, as named there: D-Net = features + cost_volume
MODULES = ('features', 'cost_volume', 'knet', 'rnet')


@dataclasses.dataclass
class TrainConfig:
    """Everything a training run depends on (stored in every checkpoint's state.json)."""
    preset: str = _params.default('preset')
    run_dir: str = 'train_runs/lite'
    export_path: Optional[str] = None     # default: dpv_sensor/weights/<preset>.safetensors
    width: int = 128                      # training image size (multiple of 4)
    height: int = 96
    extra_sizes: Tuple[Tuple[int, int], ...] = ()   # multi-scale: other sizes drawn per batch
    steps: int = 4000                     # total optimiser steps (cosine schedule length)
    batch_size: int = 2
    unroll: int = 2                       # K filter steps per sample
    window: int = _params.default('window_size')
    ref_position: str = 'last'            # validation window (and training when ref_mix is off)
    ref_mix: bool = True                  # train on centered and causal windows (drawn per batch)
    gap_min: int = 2
    gap_max: int = 6
    lr: float = 1e-3
    min_lr_ratio: float = 0.05
    warmup: int = 100
    weight_decay: float = 1e-4
    clip: float = 1.0
    aux_weight: float = 0.5
    seed: int = 0                         # torch init seed; the data seeds are seed_base + ...
    seed_base: int = TRAIN_SEED_BASE
    num_workers: int = 1
    threads: int = 1                      # torch CPU threads (1: shared machines oversubscribe badly)
    device: str = 'auto'
    amp: str = 'auto'                     # auto | off | bf16 | fp16 (see resolve_amp)
    ckpt_every: int = 100
    keep_checkpoints: int = 3
    log_every: int = 10
    val_every: int = 200
    val_seeds: Tuple[int, ...] = tuple(range(0, 6))
    val_keyframes: int = 8                # keyframes rendered per validation sequence
    val_gap: int = 4
    val_width: int = 0                    # 0: training size
    val_height: int = 0
    folders: Tuple[str, ...] = ()         # extra sequence folders mixed into training (never held-out ones)
    folder_prob: float = 0.0
    augment: bool = True
    select_metric: str = 'abs_rel_knet'   # validation score that decides exports (lower is better), see select_score
    # also validate with odometry-like poses: (rel. translation, deg) per step
    val_pose_noise: Tuple[float, float] = (0.0, 0.0)
    init_weights: Optional[str] = None    # start from an exported .safetensors instead of random
    startup_prob: float = 0.0             # share of stream-start runs (1, 2, 3, 4 sources; causal windows)
    pose_noise_prob: float = 0.0          # share of samples with odometry-like pose errors (depths exact)
    pose_noise_rot_deg: float = 0.7       # their largest rotation error per keyframe step (deg)
    pose_noise_trans_rel: float = 0.05    # their largest translation error per step (fraction of the step)
    world_scale_prob: float = 0.0         # share of samples whose world (depths, translations) is scaled
    world_scale: Tuple[float, float] = (0.5, 1.6)   # ... by a log-uniform factor in this range
    max_minutes: float = 0.0              # stop (with a checkpoint) after this wall time; 0 = no limit
    train_modules: Tuple[str, ...] = ()   # sub-networks the optimiser updates (see MODULES); () = all of them
    val_stream_seeds: Tuple[int, ...] = ()          # also stream these held-out seeds through the Estimator
    val_stream_frames: int = 60                     # frames per streamed sequence (320x240, 30 Hz)
    val_stream_pose_noise: Tuple[float, float] = (0.03, 0.5)   # its noisy-pose pass ((0, 0): GT poses only)

    def resolved_export(self) -> str:
        if self.export_path:
            return self.export_path
        return str(pathlib.Path(__file__).resolve().parents[1] / 'weights' / f'{self.preset}.safetensors')

    # tuple-valued fields (lists in JSON) and how their items are read back
    _TUPLE_FIELDS = {'val_seeds': int, 'folders': str, 'extra_sizes': tuple, 'val_pose_noise': float,
                     'train_modules': str, 'val_stream_seeds': int, 'val_stream_pose_noise': float,
                     'world_scale': float}

    def to_json(self) -> Dict:
        d = dataclasses.asdict(self)
        for k, item in self._TUPLE_FIELDS.items():
            d[k] = [list(v) if item is tuple else v for v in getattr(self, k)]
        return d

    @classmethod
    def from_json(cls, d: Dict) -> 'TrainConfig':
        known = {f.name for f in dataclasses.fields(cls)}
        kw = {k: v for k, v in d.items() if k in known}
        for k, item in cls._TUPLE_FIELDS.items():
            if k in kw:
                kw[k] = tuple(item(v) for v in kw[k])
        return cls(**kw)

    def layout(self) -> WindowLayout:
        return WindowLayout(steps=self.unroll, window=self.window, ref_position=self.ref_position)

    def stream_config(self) -> StreamConfig:
        return StreamConfig(width=self.width, height=self.height, layout=self.layout(), gap_min=self.gap_min,
                            gap_max=self.gap_max, seed_base=self.seed_base,
                            augment=Augment(enabled=self.augment), folders=tuple(self.folders),
                            folder_prob=self.folder_prob, extra_sizes=tuple(tuple(s) for s in self.extra_sizes),
                            size_group=self.batch_size,
                            ref_positions=('center', 'last') if self.ref_mix else (),
                            startup_prob=self.startup_prob, pose_noise_prob=self.pose_noise_prob,
                            pose_noise_rot_deg=self.pose_noise_rot_deg, pose_noise_trans_rel=self.pose_noise_trans_rel,
                            world_scale_prob=self.world_scale_prob, world_scale=tuple(self.world_scale))

    def check(self) -> 'TrainConfig':
        for s in self.val_seeds:
            if s not in VAL_SEEDS:
                raise ValueError(f'validation seed {s} is outside the held-out range {VAL_SEEDS}')
        if self.seed_base < TRAIN_SEED_BASE:
            raise ValueError(f'seed_base must be >= {TRAIN_SEED_BASE}')
        for f in self.folders:
            check_not_heldout(f)
        if self.width % 4 or self.height % 4:
            raise ValueError('width and height must be multiples of 4')
        if len(self.val_pose_noise) != 2 or min(self.val_pose_noise) < 0:
            raise ValueError(f'val_pose_noise must be (relative translation, rotation deg) >= 0, '
                             f'got {self.val_pose_noise}')
        spec = self.stream_spec()
        parse_select_metric(self.select_metric, noisy_validation=max(self.val_pose_noise) > 0,
                            stream_validation=spec.enabled, stream_noisy_validation=spec.noisy)
        unknown = set(self.train_modules) - set(MODULES)
        if unknown:
            raise ValueError(f'train_modules: unknown {sorted(unknown)}; choose from {MODULES}')
        return self

    def stream_spec(self) -> StreamValidationSpec:
        """The streaming validation (:mod:`.stream_validation`); its filter modes are knet plus the
        selection metric's mode."""
        modes = ['knet']
        sel = self.select_metric
        if sel.startswith(STREAM_PREFIX):
            try:
                mode = parse_select_metric(sel).mode
            except ValueError:
                mode = 'knet'
            if mode not in modes:
                modes.append(mode)
        return StreamValidationSpec(seeds=tuple(self.val_stream_seeds), frames=int(self.val_stream_frames),
                                    pose_noise=tuple(self.val_stream_pose_noise), modes=tuple(modes)).check()

    def trains(self, module: str) -> bool:
        return not self.train_modules or module in self.train_modules

    @property
    def measurement_trained(self) -> bool:
        """Whether D-Net (features or cost volume) gets gradients; if not, it runs without autograd."""
        return self.trains('features') or self.trains('cost_volume')


class SelectMetric(NamedTuple):
    metric: str         # a key of the validation entries, e.g. abs_rel
    mode: str           # filter mode
    poses: str          # 'clean' (GT poses), 'noisy' or 'both' (the mean of the two)
    stream: bool        # from the streaming validation (stream_* entries) instead of the window validation


def parse_select_metric(name: str, noisy_validation: bool = True, stream_validation: bool = True,
                        stream_noisy_validation: bool = True) -> SelectMetric:
    """``[stream_]<metric>_<mode>[_noisy|_both]`` -> :class:`SelectMetric`: e.g. ``abs_rel_knet`` (GT poses),
    ``abs_rel_knet_noisy`` (the noisy-pose validation), ``abs_rel_knet_both`` (the mean of the two), and
    ``stream_abs_rel_knet_both`` for the same from the streaming validation (``val_stream_seeds``).
    The flags say which validations the run has; naming a missing one is an error."""
    stream = name.startswith(STREAM_PREFIX)
    if stream:
        name = name[len(STREAM_PREFIX):]
    parts = name.rsplit('_', 2)
    poses = 'clean'
    if len(parts) == 3 and parts[2] in ('noisy', 'both'):
        metric, mode, poses = parts[0], parts[1], parts[2]
    else:
        metric, mode = name.rsplit('_', 1) if '_' in name else (name, '')
    if mode not in FILTER_MODES or not metric:
        raise ValueError(f'select_metric {name!r}: expected <metric>_<{"|".join(FILTER_MODES)}>[_noisy|_both]')
    if stream and not stream_validation:
        raise ValueError(f'select_metric {STREAM_PREFIX}{name!r} needs the streaming validation (val_stream_seeds)')
    if stream and poses != 'clean' and not stream_noisy_validation:
        raise ValueError(f"select_metric {STREAM_PREFIX}{name!r} needs the streaming validation's noisy poses "
                         '(val_stream_pose_noise > 0)')
    if not stream and poses != 'clean' and not noisy_validation:
        raise ValueError(f'select_metric {name!r} needs the noisy-pose validation (val_pose_noise > 0)')
    return SelectMetric(metric, mode, poses, stream)


def select_score(metrics: Dict, name: str) -> Optional[float]:
    """The validation score ``name`` (see :func:`parse_select_metric`) from :meth:`Trainer.validate`'s metrics;
    None when it is missing."""
    metric, mode, poses, stream = parse_select_metric(name)
    if stream:
        clean, noisy = stream_metric_key(mode, noisy=False), stream_metric_key(mode, noisy=True)
    else:
        clean, noisy = f'net_{mode}', f'noisy_net_{mode}'
    keys = {'clean': [clean], 'noisy': [noisy], 'both': [clean, noisy]}[poses]
    vals = [metrics.get(k, {}).get(metric) for k in keys]
    if any(v is None for v in vals):
        return None
    return float(np.mean(vals))
