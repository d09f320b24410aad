"""End-to-end NLL training of D-Net, K-Net and R-Net with the DPV filter unrolled (paper sec. 3.3).

One training sample is a run of M = K + 4 consecutive keyframes (see :mod:`.dataset`). For each of
the K unrolled filter steps j the network measures the quarter-resolution DPV of step j's reference
from its five-frame window (D-Net), the filter ``DPVFilter(mode='knet', knet=model.knet)`` predicts the
previous belief into the new camera and fuses the measurement (K-Net), and R-Net upsamples the
filtered belief to full resolution. Gradients flow through all K steps, so K-Net is trained on the
situations it meets at run time (a warped prior that is right in most voxels and wrong at
disocclusions) and learns where to damp.

Loss (per sample, averaged over the batch)::

    L = 1/K sum_j NLL(R(filter_j), d_gt)  +  aux_weight * 1/K sum_j NLL(meas_j, d_gt at 1/4)

The first term is the paper's loss (NLL of the GT depth under the full-resolution DPV, at every
unrolled step). The second is an auxiliary NLL on D-Net's own quarter-resolution measurement: it
gives the feature extractor a direct gradient that does not have to pass through K-Net and R-Net
(both start near the identity) and keeps the measurement itself calibrated - the filter assumes a
calibrated likelihood. It speeds up learning in a short CPU budget; ``--aux-weight 0`` gives the
paper's loss exactly.

Partial fine-tuning (``train_modules``, e.g. ``('knet',)``): only the named sub-networks of DPVNet get
updated; the others are frozen. Without features and cost_volume, D-Net runs without autograd and the
auxiliary term is dropped, which makes long unrolls of K-Net affordable on a CPU.

Optimiser: AdamW, lr 1e-3 with linear warm-up and cosine decay, weight decay only on conv
weights, gradient-norm clipping. The paper used Adam at 1e-5 for 20 epochs on a GPU over tens of
thousands of real frames; with a CPU budget of a few thousand steps of batch 2-4, 1e-5 would barely
move the weights, and our nets have no batch norm but Fixup-like scaled initialisation, which is
stable at 1e-3 with clipping. AMP: bfloat16 (or float16 with a GradScaler) on CUDA, bfloat16 on CPUs with
native kernels (see :func:`resolve_amp`).

Checkpoints (every ``ckpt_every`` steps, and at the end/interrupt) are directories
``<run>/checkpoints/step_XXXXXXX/`` with ``model.safetensors`` (weights), ``optimizer.safetensors``
(AdamW moments, RNG state) and ``state.json`` (step, history, lr schedule, GradScaler, the data
cursor); ``<run>/checkpoints/latest.json`` is replaced atomically and names the newest complete one.
No pickle anywhere: ``--resume`` reads only safetensors and JSON.

Validation (every ``val_every`` steps = one "epoch"; rank 0) runs held-out synthetic seeds (0..99,
never produced by the training stream) through the same unrolled pipeline in the filter modes
none / global / knet and reports abs_rel, delta1, the confident-half ratio and the NLL of the GT
before the filter (D-Net measurement) and after it; the classical ZNCC model is scored once on the
same windows for comparison. With ``val_stream_seeds`` it also streams whole held-out sequences
through the product's Estimator (:mod:`.stream_validation`; GT and odometry-like poses), which is how
the node uses the weights: ``stream_abs_rel_knet_both`` and the like select exports on that.
Plots: ``<run>/loss_curves.png``, ``<run>/val_montage_XXXXXXX.png``.
Whenever the validation score improves, the weights are exported atomically (temp file + rename)
to the export path with metadata via :func:`dpv_sensor.core.nets.checkpoint.save_checkpoint`.

Distributed: under ``torchrun`` (WORLD_SIZE > 1) a process group is initialised (NCCL on CUDA, Gloo
otherwise), the unrolled model is wrapped in DistributedDataParallel, every rank streams its own
disjoint scene seeds (seed = base + i * world + rank) and only rank 0 validates and writes files.
"""
from __future__ import annotations

import dataclasses
import datetime
import json
import math
import os
import pathlib
import shutil
import sys
import time
from typing import Dict, List, NamedTuple, Optional, Sequence as Seq, Tuple

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from dpv_sensor.core import dpv as dpvops
from dpv_sensor.common import code_version, to_jsonable
from dpv_sensor import params as _params
from dpv_sensor.core import geometry
from dpv_sensor.training.dataset import (TRAIN_SEED_BASE, VAL_SEEDS, Augment, SceneStream, StreamConfig, WindowLayout,
                      check_not_heldout, sample_from_sequence)
from dpv_sensor.training.stream_validation import (STREAM_PREFIX, StreamValidationSpec, StreamValidator,
                                                   stream_metric_key)
from dpv_sensor.core.nets.model import cpu_bf16_fast

__all__ = ['TrainConfig', 'UnrolledModel', 'Trainer', 'train', 'run_unrolled', 'measure_steps',
           'filter_steps', 'evaluate_batches', 'render_validation_batches', 'save_training_state',
           'load_training_state', 'latest_checkpoint', 'export_weights', 'plot_curves', 'code_version',
           'resolve_amp']

FILTER_MODES = ('none', 'global', 'knet')
# the sub-networks of DPVNet, as named there: D-Net = features + cost_volume
MODULES = ('features', 'cost_volume', 'knet', 'rnet')


# ----------------------------------------------------------------------------------------------
# configuration
# ----------------------------------------------------------------------------------------------

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
                     'train_modules': str, 'val_stream_seeds': int, 'val_stream_pose_noise': float}

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
                            pose_noise_rot_deg=self.pose_noise_rot_deg, pose_noise_trans_rel=self.pose_noise_trans_rel)

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


# ----------------------------------------------------------------------------------------------
# the unrolled pipeline
# ----------------------------------------------------------------------------------------------

def _pick(x: torch.Tensor, idx: int) -> torch.Tensor:
    return x[:, idx]


def measure_steps(model, batch: Dict[str, torch.Tensor], steps: Optional[Seq[int]] = None) -> List[Dict]:
    """D-Net measurement of every unrolled step of a batch (see :mod:`.dataset` for the layout).

    Returns per step a dict: logp_q (B,D,h,w), K_vol, feats, image (B,3,H,W), gt (B,H,W),
    T_world_ref (B,4,4), stamp (float).
    """
    from dpv_sensor.core.nets.dnet import ImageFeatures
    images, poses, K = batch['images'], batch['poses'], batch['K']
    ref_idx = batch['ref_idx'][0].tolist()
    src_idx = batch['src_idx'][0].tolist()
    B, M = images.shape[:2]
    # every keyframe's features once (a keyframe serves as reference and as source of several steps)
    fa = model.extract_features(images.reshape(B * M, *images.shape[2:]))
    fusion = fa.fusion.reshape(B, M, *fa.fusion.shape[1:])
    half = fa.half.reshape(B, M, *fa.half.shape[1:])
    out = []
    counts = batch['src_count'][0].tolist() if 'src_count' in batch else None
    for j in (range(len(ref_idx)) if steps is None else steps):
        r, ss = ref_idx[j], src_idx[j]
        if counts is not None:
            ss = ss[len(ss) - int(counts[j]):]
        ref = images[:, r]
        T_world_ref = poses[:, r]
        T_src_world = geometry.invert_se3(poses[:, ss].reshape(-1, 4, 4)).reshape(B, len(ss), 4, 4)
        T_src_ref = T_src_world @ T_world_ref[:, None]
        logp_q, K_vol, feats = model.measure(ref, None, K, T_src_ref, src_features=fusion[:, ss],
                                             ref_features=ImageFeatures(fusion[:, r], half[:, r]))
        out.append(dict(logp_q=logp_q, K_vol=K_vol, feats=feats, image=ref, gt=batch['depths'][:, r],
                        T_world_ref=T_world_ref, stamp=float(batch['stamps'][0, r])))
    return out


def make_filter(model, mode: str, damping: float = _params.default('damping')):
    """A fresh DPVFilter in ``mode`` (K-Net = the model's, so gradients reach it)."""
    from dpv_sensor.core.filter import DPVFilter
    # generous reset thresholds: training windows never need a reset (and a reset would cut the unroll)
    return DPVFilter(mode=mode, damping=damping, knet=model.knet if mode == 'knet' else None,
                     max_time_gap=1e9, max_translation=1e9, max_rotation_deg=1e9)


def quarter_gt(gt_bhw: torch.Tensor, hw: Tuple[int, int]) -> torch.Tensor:
    """GT on the quarter-resolution DPV grid: volume pixel j sits on full-resolution pixel 4j."""
    h, w = hw
    return gt_bhw[:, ::4, ::4][:, :h, :w]


def filter_steps(model, meas: List[Dict], depths_d: torch.Tensor, mode: str, refine: bool = True) -> List[Dict]:
    """Run the filter over the measured steps and refine each belief; returns per step
    ``filtered_q`` (quarter-res log-DPV after the update) and ``logp_full`` (R-Net output)."""
    filt = make_filter(model, mode)
    out = []
    for m in meas:
        st = filt.step(m['logp_q'], m['K_vol'], m['T_world_ref'], m['stamp'], depths_d, image_b3hw=m['image'])
        res = dict(filtered_q=st.logp_bdhw, reset=st.reset_reason)
        if refine:
            res['logp_full'] = model.refine(st.logp_bdhw, m['feats'], m['image'])
        out.append(res)
    return out


def run_unrolled(model, batch: Dict[str, torch.Tensor], depths_d: torch.Tensor, aux_weight: float = 0.5,
                 mode: str = 'knet', measure_grad: bool = True) -> Tuple[torch.Tensor, Dict[str, float]]:
    """The training loss of one batch (see the module docstring) and scalar statistics.

    ``measure_grad=False`` runs D-Net without autograd (it is frozen) and drops the auxiliary term, which
    would then carry no gradient.
    """
    with torch.set_grad_enabled(measure_grad and torch.is_grad_enabled()):
        meas = measure_steps(model, batch)
    res = filter_steps(model, meas, depths_d, mode)
    nll_full, nll_q = [], []
    for m, r in zip(meas, res):
        nll_full.append(dpvops.nll(r['logp_full'].float(), depths_d, m['gt']))
        gq = quarter_gt(m['gt'], m['logp_q'].shape[-2:])
        nll_q.append(dpvops.nll(m['logp_q'].float(), depths_d, gq))
    l_full = torch.stack(nll_full).mean()
    l_q = torch.stack(nll_q).mean()
    loss = l_full + aux_weight * l_q if aux_weight > 0 and measure_grad else l_full
    stats = {'loss': float(loss.detach()), 'nll_full': float(l_full.detach()), 'nll_meas_q': float(l_q.detach()),
             'resets': sum(r['reset'] is not None for r in res[1:])}
    for j, v in enumerate(nll_full):
        stats[f'nll_full_{j}'] = float(v.detach())
    return loss, stats


class UnrolledModel(nn.Module):
    """nn.Module wrapper whose forward is the whole unrolled loss (what DDP wraps)."""

    def __init__(self, model: nn.Module, depths_d: torch.Tensor, aux_weight: float, measure_grad: bool = True):
        super().__init__()
        self.model = model
        self.register_buffer('depths_d', depths_d, persistent=False)
        self.aux_weight = float(aux_weight)
        self.measure_grad = bool(measure_grad)

    def forward(self, batch: Dict[str, torch.Tensor]):
        loss, stats = run_unrolled(self.model, batch, self.depths_d, self.aux_weight, measure_grad=self.measure_grad)
        return loss, stats


# ----------------------------------------------------------------------------------------------
# validation
# ----------------------------------------------------------------------------------------------

def render_validation_batches(seeds: Seq[int], num_keyframes: int, gap: int, width: int, height: int,
                              layout: WindowLayout, split: str = 'val') -> List[Dict[str, torch.Tensor]]:
    """One batch (B = 1) per held-out seed: ``num_keyframes`` keyframes ``gap`` frames apart, rendered
    at width x height, no augmentation, unrolled over all complete windows.

    ``split='train'`` renders the same kind of batches from *training* seeds (>= ``TRAIN_SEED_BASE``),
    e.g. to tune a baseline's parameters on training data only; each split refuses the other's seeds."""
    from dpv_sensor.data.synthetic import render_sequence
    steps = num_keyframes - layout.window + 1
    if steps < 1:
        raise ValueError(f'need at least {layout.window} validation keyframes')
    lay = WindowLayout(steps=steps, window=layout.window, ref_position=layout.ref_position)
    out = []
    if split not in ('val', 'train'):
        raise ValueError(f"split must be 'val' or 'train', got {split!r}")
    for s in seeds:
        if split == 'val' and s not in VAL_SEEDS:
            raise ValueError(f'validation seed {s} is not held out')
        if split == 'train' and (s in VAL_SEEDS or s < TRAIN_SEED_BASE):
            raise ValueError(f'seed {s} is not a training seed (need >= {TRAIN_SEED_BASE}; '
                             f'{VAL_SEEDS.start}..{VAL_SEEDS.stop - 1} are held out)')
        ids = [k * gap for k in range(num_keyframes)]
        seq = render_sequence(int(s), ids[-1] + 1, width=width, height=height, lazy=True)
        smp = sample_from_sequence(seq, ids, lay, np.random.default_rng(0), augment=None, seed=int(s))
        out.append({k: v[None] for k, v in smp.items()})
    return out


def corrupt_validation_batches(batches: List[Dict[str, torch.Tensor]], trans_noise_rel: float, rot_noise_deg: float
                               ) -> List[Dict[str, torch.Tensor]]:
    """Copies of validation batches whose poses carry odometry-like errors (``data.trajectory.corrupt_trajectory``:
    per keyframe step a rotation of ``rot_noise_deg`` about a random axis and a translation error of
    ``trans_noise_rel`` of the step, accumulating), seeded by the batch's position so every validation sees the
    same poses. Images and depths are untouched: the score says how well the nets cope with imperfect poses."""
    from dpv_sensor.data.trajectory import corrupt_trajectory
    out = []
    for j, b in enumerate(batches):
        poses = [T.double().numpy() for T in b['poses'][0]]
        noisy = corrupt_trajectory(poses, trans_noise_rel=float(trans_noise_rel), rot_noise_deg=float(rot_noise_deg),
                                   seed=1000 + j)
        nb = dict(b)
        nb['poses'] = torch.from_numpy(np.stack(noisy).astype(np.float32))[None].to(b['poses'].dtype)
        out.append(nb)
    return out


def _to_device(batch: Dict[str, torch.Tensor], device) -> Dict[str, torch.Tensor]:
    return {k: (v.to(device, non_blocking=True) if torch.is_tensor(v) else v) for k, v in batch.items()}


def _np(x: torch.Tensor) -> np.ndarray:
    return x.detach().float().cpu().numpy()


@torch.no_grad()
def evaluate_batches(model, batches: List[Dict[str, torch.Tensor]], depths_d: torch.Tensor, device,
                     modes: Seq[str] = FILTER_MODES, classical=None, keep_last: bool = True,
                     curves: bool = False, readout: str = dpvops.DEFAULT_READOUT,
                     confidence: str = dpvops.DEFAULT_CONFIDENCE,
                     confidence_ratio: float = _params.default('confidence_ratio')) -> Dict:
    """Score the model (and optionally a classical measurement model) on validation batches.

    Depth and confidence come from the DPVs with ``readout`` (:func:`dpv_sensor.core.dpv.depth_estimate`;
    'auto' resolves per source with :func:`dpv_sensor.core.dpv.resolve_readout`).

    Returns ``{'<source>_<mode>': {abs_rel, delta1, confident_half_ratio, ause, aurg, nll_meas_q,
    nll_filtered_q, nll_full}, ..., 'examples': [...]}`` with ``source`` = 'net' or 'classical'. NLLs
    are means over frames of :func:`dpv_sensor.core.dpv.nll`; depth metrics are frame means of
    :class:`dpv_sensor.evaluation.metrics.MetricAccumulator` (metric, not median-scaled); ``ause`` is the frame
    mean, ``aurg`` (area of random minus sparsification, > 0 = better than random) that of the mean
    curve. With ``curves=True`` each entry also carries ``sparsification_curves``
    (:meth:`MetricAccumulator.mean_curves`: numpy arrays, not JSON).
    """
    from dpv_sensor.evaluation.metrics import MetricAccumulator
    was_training = model.training if model is not None else False
    if model is not None:
        model.eval()
    sources = []
    if model is not None:
        sources.append(('net', model))
    if classical is not None:
        sources.append(('classical', classical))
    results: Dict = {}
    examples = []
    for name, src in sources:
        ro = dpvops.resolve_readout(readout, learned=name == 'net')
        accs = {m: MetricAccumulator() for m in modes}
        nlls = {m: {'nll_meas_q': [], 'nll_filtered_q': [], 'nll_full': []} for m in modes}
        for bi, batch in enumerate(batches):
            batch = _to_device(batch, device)
            if name == 'net':
                meas = measure_steps(src, batch)
            else:
                meas = _classical_steps(src, batch)
            for mode in modes:
                if name == 'classical' and mode == 'knet':
                    continue
                if name == 'net':
                    res = filter_steps(src, meas, depths_d, mode)
                else:
                    res = filter_steps(_NoKnet(), meas, depths_d, mode, refine=False)
                for j, (m, r) in enumerate(zip(meas, res)):
                    gt = m['gt']
                    gq = quarter_gt(gt, m['logp_q'].shape[-2:])
                    nlls[mode]['nll_meas_q'].append(float(dpvops.nll(m['logp_q'].float(), depths_d, gq)))
                    nlls[mode]['nll_filtered_q'].append(float(dpvops.nll(r['filtered_q'].float(), depths_d, gq)))
                    if 'logp_full' in r:
                        lp = r['logp_full'].float()
                        nlls[mode]['nll_full'].append(float(dpvops.nll(lp, depths_d, gt)))
                        depth = dpvops.depth_estimate(lp, depths_d, ro)
                        conf = dpvops.published_confidence(lp, depths_d, depth, confidence, confidence_ratio)
                    else:                                   # classical: upsample the quarter-res maps
                        lq = r['filtered_q'].float()
                        H, W = gt.shape[-2:]
                        dq = dpvops.depth_estimate(lq, depths_d, ro)
                        depth = _upsample_map(dq, (H, W))
                        conf = _upsample_map(dpvops.published_confidence(lq, depths_d, dq, confidence,
                                                                         confidence_ratio), (H, W))
                    for b in range(gt.shape[0]):
                        accs[mode].add(_np(depth[b]), _np(gt[b]), confidence=_np(conf[b]))
                    if keep_last and bi == 0 and j == len(meas) - 1:
                        examples.append(dict(source=name, mode=mode, image=_np(m['image'][0]).transpose(1, 2, 0),
                                             gt=_np(gt[0]), depth=_np(depth[0]), conf=_np(conf[0])))
        for mode in modes:
            if name == 'classical' and mode == 'knet':
                continue
            s = accs[mode].summary()
            fm = s['metric']['frame_mean']
            conf = s.get('confidence', {})
            entry = {'abs_rel': fm['abs_rel'], 'delta1': fm['delta1'], 'rmse': fm['rmse'],
                     'confident_half_ratio': conf.get('confident_half_ratio_frame_mean', float('nan')),
                     'confident_half_ratio_pooled': conf.get('confident_half_ratio_pooled', float('nan')),
                     'ause': conf.get('ause_frame_mean', float('nan')),
                     'aurg': conf.get('aurg_of_mean_curve', float('nan')),
                     'frames': s['num_frames']}
            if curves:
                entry['sparsification_curves'] = accs[mode].mean_curves()
            for k, v in nlls[mode].items():
                entry[k] = float(np.mean(v)) if v else float('nan')
            results[f'{name}_{mode}'] = entry
    if model is not None and was_training:
        model.train()
    results['examples'] = examples
    return results


class _NoKnet:
    knet = None


def _upsample_map(x_bhw: torch.Tensor, hw) -> torch.Tensor:
    """Quarter-res map (pixel j on full pixel 4j) to full resolution, bilinear on that grid."""
    B, h, w = x_bhw.shape
    H, W = int(hw[0]), int(hw[1])
    u = torch.arange(W, dtype=x_bhw.dtype, device=x_bhw.device) / 4.0
    v = torch.arange(H, dtype=x_bhw.dtype, device=x_bhw.device) / 4.0
    gx = 2.0 * u / max(w - 1, 1) - 1.0
    gy = 2.0 * v / max(h - 1, 1) - 1.0
    gyy, gxx = torch.meshgrid(gy, gx, indexing='ij')
    grid = torch.stack([gxx, gyy], -1)[None].expand(B, H, W, 2)
    return F.grid_sample(x_bhw[:, None], grid, mode='bilinear', padding_mode='border', align_corners=True)[:, 0]


def _classical_steps(classical, batch) -> List[Dict]:
    """Like :func:`measure_steps` for a :class:`dpv_sensor.core.classical.ClassicalMeasurement`."""
    images, poses, K = batch['images'], batch['poses'], batch['K']
    ref_idx = batch['ref_idx'][0].tolist()
    src_idx = batch['src_idx'][0].tolist()
    out = []
    for j in range(len(ref_idx)):
        r, ss = ref_idx[j], src_idx[j]
        T_world_ref = poses[:, r]
        T_src_world = geometry.invert_se3(poses[:, ss].reshape(-1, 4, 4)).reshape(poses.shape[0], len(ss), 4, 4)
        logp_q, K_vol = classical(images[:, r], images[:, ss], K, T_src_world @ T_world_ref[:, None])
        out.append(dict(logp_q=logp_q, K_vol=K_vol, feats=None, image=images[:, r], gt=batch['depths'][:, r],
                        T_world_ref=T_world_ref, stamp=float(batch['stamps'][0, r])))
    return out


def save_montage(examples: List[Dict], path: str, d_min: float, d_max: float, title: str = '') -> None:
    """PNG: per (source, mode) row: image | GT | depth | confidence | |error|/GT."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    if not examples:
        return
    rows = len(examples)
    fig, axes = plt.subplots(rows, 5, figsize=(13, 2.2 * rows + 0.4), squeeze=False)
    gt0 = examples[0]['gt']
    vmax = float(np.percentile(gt0[gt0 > 0], 99)) if (gt0 > 0).any() else d_max
    for r, ex in enumerate(examples):
        gt = ex['gt']
        err = np.where(gt > 0, np.abs(ex['depth'] - gt) / np.maximum(gt, 1e-6), np.nan)
        panels = [(np.clip(ex['image'], 0, 1), None, 'image'), (np.where(gt > 0, gt, np.nan), 'turbo', 'GT depth'),
                  (ex['depth'], 'turbo', f"{ex['source']} {ex['mode']}"), (ex['conf'], 'viridis', 'confidence'),
                  (err, 'magma', f'abs rel err (mean {np.nanmean(err):.3f})')]
        for c, (img, cmap, name) in enumerate(panels):
            ax = axes[r, c]
            if cmap is None:
                ax.imshow(img)
            elif cmap == 'turbo':
                ax.imshow(img, cmap=cmap, vmin=d_min, vmax=vmax)
            elif cmap == 'magma':
                ax.imshow(img, cmap=cmap, vmin=0, vmax=0.3)
            else:
                ax.imshow(img, cmap=cmap, vmin=0, vmax=1)
            ax.set_title(name, fontsize=8)
            ax.axis('off')
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    _atomic_savefig(fig, path)
    plt.close(fig)


def _atomic_savefig(fig, path: str) -> None:
    tmp = f'{path}.tmp.png'
    fig.savefig(tmp, dpi=90)
    os.replace(tmp, path)


def plot_curves(history: Dict, path: str, reference: Optional[Dict] = None) -> None:
    """PNG with the training loss (raw and smoothed, per term) and the validation metrics over steps.

    ``reference``: validation results of the classical model, drawn as horizontal lines."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    tr = history.get('train', [])
    if tr:
        steps = np.array([t['step'] for t in tr])
        for key, colour in (('loss', 'k'), ('nll_full', 'tab:blue'), ('nll_meas_q', 'tab:orange')):
            y = np.array([t.get(key, np.nan) for t in tr], np.float64)
            axes[0].plot(steps, y, color=colour, alpha=0.25, lw=0.8)
            k = max(1, min(25, len(y) // 10))
            if len(y) >= k:
                sm = np.convolve(y, np.ones(k) / k, mode='valid')
                axes[0].plot(steps[k - 1:], sm, color=colour, lw=1.6, label=key)
        axes[0].set_xlabel('step')
        axes[0].set_ylabel('NLL (nats)')
        axes[0].set_title('training loss')
        axes[0].legend(fontsize=8)
        axes[0].grid(alpha=0.3)
    va = history.get('val', [])
    if va:
        steps = np.array([v['step'] for v in va])
        for mode, colour in (('none', 'tab:gray'), ('global', 'tab:green'), ('knet', 'tab:red')):
            y = [v['metrics'].get(f'net_{mode}', {}).get('abs_rel', np.nan) for v in va]
            axes[1].plot(steps, y, 'o-', color=colour, label=f'net {mode}')
            yn = np.array([v['metrics'].get(f'noisy_net_{mode}', {}).get('abs_rel', np.nan) for v in va], np.float64)
            if np.isfinite(yn).any():
                axes[1].plot(steps, yn, 'x--', color=colour, label=f'net {mode}, noisy poses')
            for key, marker in ((stream_metric_key(mode, False), 'D-'), (stream_metric_key(mode, True), 'D:')):
                ys = np.array([v['metrics'].get(key, {}).get('abs_rel', np.nan) for v in va], np.float64)
                if np.isfinite(ys).any():
                    axes[1].plot(steps, ys, marker, color=colour, mfc='none',
                                 label=f'net {mode}, streamed' + (', noisy poses' if 'noisy' in key else ''))
            y2 = [v['metrics'].get(f'net_{mode}', {}).get('nll_full', np.nan) for v in va]
            axes[2].plot(steps, y2, 'o-', color=colour, label=f'net {mode} (full res)')
        y3 = [v['metrics'].get('net_knet', {}).get('nll_meas_q', np.nan) for v in va]
        axes[2].plot(steps, y3, 's--', color='tab:orange', label='net measurement (1/4 res, before filter)')
        if reference:
            for mode, ls in (('none', ':'), ('global', '--')):
                ref = reference.get(f'classical_{mode}')
                if ref:
                    axes[1].axhline(ref['abs_rel'], color='tab:purple', ls=ls, label=f'classical {mode}')
                    axes[2].axhline(ref['nll_filtered_q'], color='tab:purple', ls=ls, label=f'classical {mode} (1/4)')
        axes[1].set_title('validation abs_rel (held-out seeds)')
        axes[2].set_title('validation NLL of GT')
        for ax in axes[1:]:
            ax.set_xlabel('step')
            ax.legend(fontsize=7)
            ax.grid(alpha=0.3)
    fig.tight_layout()
    _atomic_savefig(fig, path)
    plt.close(fig)


# ----------------------------------------------------------------------------------------------
# checkpoints (safetensors + JSON, never pickle)
# ----------------------------------------------------------------------------------------------

def _atomic_write_text(path: pathlib.Path, text: str) -> None:
    tmp = path.with_name(path.name + '.tmp')
    tmp.write_text(text)
    os.replace(tmp, path)


_json_safe = to_jsonable        # the one JSON sanitiser (dpv_sensor.common)


def _optimizer_to_flat(optimizer: torch.optim.Optimizer) -> Tuple[Dict[str, torch.Tensor], Dict]:
    sd = optimizer.state_dict()
    tensors, scalars = {}, {}
    for pid, st in sd['state'].items():
        for k, v in st.items():
            if torch.is_tensor(v):
                flat = v.detach().cpu().contiguous()
                tensors[f'state.{pid}.{k}'] = flat.reshape(-1) if v.dim() == 0 else flat
                if v.dim() == 0:
                    scalars[f'{pid}.{k}'] = 'scalar'
            else:
                scalars[f'{pid}.{k}'] = v
    return tensors, {'param_groups': _json_safe(sd['param_groups']), 'scalars': scalars}


def _optimizer_from_flat(tensors: Dict[str, torch.Tensor], meta: Dict) -> Dict:
    state: Dict[int, Dict] = {}
    for name, v in tensors.items():
        if not name.startswith('state.'):
            continue
        _, pid, k = name.split('.', 2)
        if meta['scalars'].get(f'{pid}.{k}') == 'scalar':
            v = v.reshape(())
        state.setdefault(int(pid), {})[k] = v
    for key, v in meta['scalars'].items():
        if v != 'scalar':
            pid, k = key.split('.', 1)
            state.setdefault(int(pid), {})[k] = v
    return {'state': state, 'param_groups': meta['param_groups']}


def save_training_state(run_dir: str, step: int, model: nn.Module, optimizer: torch.optim.Optimizer,
                        state: Dict, keep: int = 3) -> pathlib.Path:
    """Write ``<run_dir>/checkpoints/step_<step>/`` and point ``latest.json`` at it (atomically)."""
    from safetensors.torch import save_file
    ck = pathlib.Path(run_dir) / 'checkpoints'
    ck.mkdir(parents=True, exist_ok=True)
    name = f'step_{step:07d}'
    tmp = ck / (name + '.tmp')
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir()
    save_file({k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}, str(tmp / 'model.safetensors'))
    opt_t, opt_meta = _optimizer_to_flat(optimizer)
    opt_t['rng.torch'] = torch.get_rng_state()
    if torch.cuda.is_available():
        opt_t['rng.cuda'] = torch.cuda.get_rng_state()
    save_file(opt_t, str(tmp / 'optimizer.safetensors'))
    full = dict(state)
    full['step'] = int(step)
    full['optimizer'] = opt_meta
    (tmp / 'state.json').write_text(json.dumps(_json_safe(full), indent=1))
    final = ck / name
    if final.exists():
        shutil.rmtree(final)
    os.replace(tmp, final)
    _atomic_write_text(ck / 'latest.json', json.dumps({'step': int(step), 'dir': name}))
    olds = sorted(p for p in ck.glob('step_*') if p.is_dir() and not p.name.endswith('.tmp') and p.name != name)
    for p in olds[:max(0, len(olds) - (keep - 1))]:
        shutil.rmtree(p, ignore_errors=True)
    return final


def latest_checkpoint(run_dir: str) -> Optional[pathlib.Path]:
    """The checkpoint directory named by ``latest.json`` (None when there is none)."""
    ck = pathlib.Path(run_dir) / 'checkpoints'
    f = ck / 'latest.json'
    if not f.is_file():
        return None
    d = ck / json.loads(f.read_text())['dir']
    return d if (d / 'state.json').is_file() else None


def load_training_state(ckpt_dir, model: nn.Module, optimizer: Optional[torch.optim.Optimizer] = None,
                        device='cpu') -> Dict:
    """Restore model (and optimizer, RNG) from a checkpoint directory; returns its state.json dict."""
    from safetensors.torch import load_file
    ckpt_dir = pathlib.Path(ckpt_dir)
    state = json.loads((ckpt_dir / 'state.json').read_text())
    sd = load_file(str(ckpt_dir / 'model.safetensors'), device=str(device))
    model.load_state_dict(sd)
    opt_t = load_file(str(ckpt_dir / 'optimizer.safetensors'))
    if optimizer is not None:
        osd = _optimizer_from_flat(opt_t, state['optimizer'])
        optimizer.load_state_dict(osd)
    if 'rng.torch' in opt_t:
        torch.set_rng_state(opt_t['rng.torch'])
    if 'rng.cuda' in opt_t and torch.cuda.is_available():
        torch.cuda.set_rng_state(opt_t['rng.cuda'])
    return state


def export_weights(model: nn.Module, path: str, metadata: Dict) -> None:
    """Export the weights with metadata via nets/checkpoint.save_checkpoint, atomically
    (write a temp file in the same folder, then rename over the target)."""
    from dpv_sensor.core.nets.checkpoint import save_checkpoint
    target = pathlib.Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.with_name(f'.{target.stem}.tmp-{os.getpid()}.safetensors')
    try:
        save_checkpoint(str(tmp), model, _json_safe(metadata))
        os.chmod(tmp, 0o644)          # a packaged file: readable by the user the node runs as
        os.replace(tmp, target)
    finally:
        if tmp.exists():
            tmp.unlink()


# ----------------------------------------------------------------------------------------------
# the trainer
# ----------------------------------------------------------------------------------------------

def _dist_env() -> Tuple[int, int, int]:
    world = int(os.environ.get('WORLD_SIZE', '1'))
    rank = int(os.environ.get('RANK', '0'))
    local = int(os.environ.get('LOCAL_RANK', '0'))
    return world, rank, local


def all_ranks(flag: bool, device, world: int) -> bool:
    """``flag`` and-ed over the ranks of the process group (just ``flag`` when ``world`` is 1)."""
    if world <= 1:
        return bool(flag)
    t = torch.tensor([1.0 if flag else 0.0], device=device)
    torch.distributed.all_reduce(t, op=torch.distributed.ReduceOp.MIN)
    return bool(t.item() > 0.5)


def _lr_at(cfg: TrainConfig, step: int) -> float:
    if step < cfg.warmup:
        return cfg.lr * (step + 1) / cfg.warmup
    t = min(1.0, (step - cfg.warmup) / max(1, cfg.steps - cfg.warmup))
    return cfg.lr * (cfg.min_lr_ratio + (1 - cfg.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * t)))


def _param_groups(model: nn.Module, weight_decay: float):
    decay, no_decay = [], []
    for _, p in model.named_parameters():
        if not p.requires_grad:
            continue
        (decay if p.dim() >= 2 else no_decay).append(p)
    return [{'params': decay, 'weight_decay': weight_decay}, {'params': no_decay, 'weight_decay': 0.0}]


def _worker_init(_):
    """Rendering workers: one thread each (torch and OpenCV), so they never oversubscribe the CPU."""
    torch.set_num_threads(1)
    try:
        import cv2
        cv2.setNumThreads(1)
    except Exception:
        pass


def resolve_amp(amp: str, device: torch.device) -> Optional[torch.dtype]:
    """The autocast dtype of a training step, or None for float32.

    CUDA: ``auto`` is bfloat16 where supported, else float16 (with a gradient scaler); ``bf16`` / ``fp16``
    force one. CPU: ``auto`` is bfloat16 where oneDNN has native kernels (:func:`cpu_bf16_fast`: AMX or
    AVX512-BF16; a lite step at 256x192 then takes 2.1 s instead of 3.8 s, and validation tracks a float32 run
    with the same seeds to 3 digits) and float32 elsewhere; ``bf16`` forces it; ``fp16`` is refused (CPU
    autocast has no float16 kernels worth using). The cost volume, filter, readout and loss stay float32.
    """
    if amp not in ('auto', 'off', 'bf16', 'fp16'):
        raise ValueError(f'amp must be auto, off, bf16 or fp16, got {amp!r}')
    if amp == 'off':
        return None
    if device.type == 'cuda':
        if amp == 'fp16' or (amp == 'auto' and not torch.cuda.is_bf16_supported()):
            return torch.float16
        return torch.bfloat16
    if amp == 'fp16':
        raise ValueError('--amp fp16 is CUDA only; on the CPU use --amp bf16 (or off)')
    if amp == 'bf16' or cpu_bf16_fast():
        return torch.bfloat16
    return None


class Trainer:
    """Owns model, optimiser, data, validation and checkpoints of one run (see the module docstring)."""

    def __init__(self, cfg: TrainConfig, resume: bool = False, quiet: bool = False, argv: Optional[List[str]] = None):
        from dpv_sensor.core.nets.model import DPVNet
        from dpv_sensor.core.nets.presets import get_preset
        self.cfg = cfg.check()
        self.quiet = quiet
        self.argv = list(argv) if argv is not None else list(sys.argv)
        self.world, self.rank, self.local_rank = _dist_env()
        self.is_main = self.rank == 0
        if cfg.device == 'auto':
            dev = f'cuda:{self.local_rank}' if torch.cuda.is_available() else 'cpu'
        else:
            dev = cfg.device
        self.device = torch.device(dev)
        if self.device.type == 'cpu':
            torch.set_num_threads(max(1, cfg.threads))
        if self.world > 1 and not torch.distributed.is_initialized():
            if self.device.type == 'cuda':
                torch.cuda.set_device(self.device)
            torch.distributed.init_process_group(backend='nccl' if self.device.type == 'cuda' else 'gloo')
        torch.manual_seed(cfg.seed)
        self.preset = get_preset(cfg.preset)
        self.model = DPVNet(self.preset).to(self.device)
        if cfg.init_weights:
            from dpv_sensor.core.nets.checkpoint import load_checkpoint
            src, self.init_meta = load_checkpoint(cfg.init_weights, preset=self.preset)
            self.model.load_state_dict(src.state_dict())
        else:
            self.init_meta = None
        self.depths = dpvops.depth_planes(self.preset.d_min, self.preset.d_max, self.preset.num_planes,
                                          device=self.device)
        for name, child in self.model.named_children():
            child.requires_grad_(cfg.trains(name))
        self.optimizer = torch.optim.AdamW(_param_groups(self.model, cfg.weight_decay), lr=cfg.lr,
                                           betas=(0.9, 0.999))
        self.amp_dtype = resolve_amp(cfg.amp, self.device)
        if self.amp_dtype is not None and self.device.type == 'cpu' and not cpu_bf16_fast():
            self._log('warning: --amp bf16 on a CPU without AVX512-BF16/AMX runs emulated and is slower than float32')
        self.scaler = torch.amp.GradScaler('cuda', enabled=self.amp_dtype == torch.float16)
        self.step = 0
        self.history: Dict = {'train': [], 'val': []}
        self.best: Optional[float] = None
        self.best_metrics: Optional[Dict] = None
        self.classical_ref: Optional[Dict] = None
        self.samples_seen = 0
        self.wall_s = 0.0
        self.run_dir = pathlib.Path(cfg.run_dir)
        if self.is_main:
            self.run_dir.mkdir(parents=True, exist_ok=True)
        if resume:
            ck = latest_checkpoint(cfg.run_dir)
            if ck is None:
                self._log(f'no checkpoint in {cfg.run_dir}/checkpoints; starting from scratch')
            else:
                st = load_training_state(ck, self.model, self.optimizer, device=self.device)
                self.step = int(st['step'])
                self.history = st.get('history', self.history)
                self.best = st.get('best')
                self.best_metrics = st.get('best_metrics')
                self.classical_ref = st.get('classical_ref')
                self.samples_seen = int(st.get('samples_seen', 0))
                self.wall_s = float(st.get('wall_s', 0.0))
                if st.get('scaler'):
                    self.scaler.load_state_dict(st['scaler'])
                self._log(f'resumed from {ck} at step {self.step}')
        self.unrolled = UnrolledModel(self.model, self.depths, cfg.aux_weight,
                                      measure_grad=cfg.measurement_trained).to(self.device)
        self.ddp = None
        if self.world > 1:
            from torch.nn.parallel import DistributedDataParallel as DDP
            self.ddp = DDP(self.unrolled, device_ids=[self.device.index] if self.device.type == 'cuda' else None)
        self._val_batches = None
        self._noisy_val_batches = None
        self.stream_validator = StreamValidator(cfg.stream_spec())

    # -- helpers --------------------------------------------------------------------------------
    def _log(self, msg: str) -> None:
        if self.is_main and not self.quiet:
            print(f'[train {datetime.datetime.now().strftime("%H:%M:%S")}] {msg}', flush=True)

    def _append_jsonl(self, name: str, row: Dict) -> None:
        if self.is_main:
            with open(self.run_dir / name, 'a') as f:
                f.write(json.dumps(_json_safe(row)) + '\n')

    def loader(self):
        """DataLoader over this rank's disjoint seed stream, continuing at the resumed sample."""
        from torch.utils.data import DataLoader
        per_rank_start = self.step * self.cfg.batch_size
        ds = SceneStream(self.cfg.stream_config(), rank=self.rank, world_size=self.world, start_index=per_rank_start)
        kw = {}
        if self.cfg.num_workers > 0:
            kw = dict(num_workers=self.cfg.num_workers, worker_init_fn=_worker_init, prefetch_factor=2,
                      persistent_workers=False)
        return DataLoader(ds, batch_size=self.cfg.batch_size, pin_memory=self.device.type == 'cuda', **kw)

    def val_batches(self):
        if self._val_batches is None:
            w = self.cfg.val_width or self.cfg.width
            h = self.cfg.val_height or self.cfg.height
            self._val_batches = render_validation_batches(self.cfg.val_seeds, self.cfg.val_keyframes,
                                                          self.cfg.val_gap, w, h, self.cfg.layout())
        return self._val_batches

    def noisy_val_batches(self):
        """The validation batches with ``val_pose_noise`` odometry-like pose errors (same poses every time)."""
        if self._noisy_val_batches is None:
            self._noisy_val_batches = corrupt_validation_batches(self.val_batches(), *self.cfg.val_pose_noise)
        return self._noisy_val_batches

    def state_dict_json(self) -> Dict:
        return {'config': self.cfg.to_json(), 'history': self.history, 'best': self.best,
                'best_metrics': self.best_metrics, 'classical_ref': self.classical_ref,
                'samples_seen': self.samples_seen, 'wall_s': self.wall_s,
                'scaler': self.scaler.state_dict() if self.scaler.is_enabled() else None,
                'code_version': code_version(), 'world_size': self.world}

    def save(self) -> None:
        if self.is_main:
            save_training_state(str(self.run_dir), self.step, self.model, self.optimizer, self.state_dict_json(),
                                keep=self.cfg.keep_checkpoints)

    def metadata(self, metrics: Dict) -> Dict:
        cfg = self.cfg
        data = {
            'description': 'synthetic scenes rendered on the fly by dpv_sensor.data.synthetic.render_sequence, '
                           'one fresh scene per sample, runs of consecutive keyframes with 5-frame windows, '
                           'GT poses and depth, photometric augmentation'
                           + (f"; {cfg.folder_prob:.0%} of the samples from the sequence folders "
                              f"{', '.join(os.path.basename(os.path.normpath(f)) for f in cfg.folders)} "
                              '(random scale and crop)' if cfg.folders and cfg.folder_prob > 0 else ''),
            'train_seed_range': [cfg.seed_base, cfg.seed_base + max(1, self.samples_seen) * self.world],
            'train_seed_rule': 'seed = seed_base + i * world_size + rank, i = 0 .. samples per rank - 1',
            'samples_seen': self.samples_seen,
            'validation_seeds': list(cfg.val_seeds),
            'validation_pose_noise': list(cfg.val_pose_noise),
            'validation_stream': ({'seeds': list(cfg.val_stream_seeds), 'frames': cfg.val_stream_frames,
                                   'pose_noise': list(cfg.val_stream_pose_noise),
                                   'how': 'every frame through dpv_sensor.stream.estimator.Estimator (node defaults)'}
                                  if cfg.val_stream_seeds else None),
            'selection_metric': cfg.select_metric,
            'held_out_seed_range': [VAL_SEEDS.start, VAL_SEEDS.stop - 1],
            'mixed_folders': [os.path.basename(os.path.normpath(f)) for f in cfg.folders],
            'folder_prob': cfg.folder_prob,
            'never_trained_on': ['sun3d_3dmatch_frag1', 'sun3d_3dmatch_frag2', 'tum_fr1_rpy', 'icl_nuim_lr_kt3',
                                 f'synthetic seeds {VAL_SEEDS.start}..{VAL_SEEDS.stop - 1}'],
            'train_size': [cfg.width, cfg.height],
            'keyframe_gap_frames': [cfg.gap_min, cfg.gap_max],
            'unrolled_steps': cfg.unroll,
            'window': cfg.window,
            'window_layouts': ['center', 'last'] if cfg.ref_mix else [cfg.ref_position],
            'validation_window': cfg.ref_position,
            'extra_sizes': [list(s) for s in cfg.extra_sizes],
        }
        data['startup_prob'] = cfg.startup_prob
        prior_steps = 0
        if self.init_meta is not None:
            prior_steps = int(self.init_meta.get('steps') or 0)
            data['initialised_from'] = {'file': os.path.basename(cfg.init_weights), 'steps': prior_steps,
                                        'training_data': self.init_meta.get('training_data'),
                                        'loss': self.init_meta.get('loss'),
                                        'optimizer': self.init_meta.get('optimizer')}
        return {
            'steps_this_run': self.step, 'steps_total': prior_steps + self.step,
            'preset': self.preset.name, 'D': self.preset.num_planes, 'd_min': self.preset.d_min,
            'd_max': self.preset.d_max, 'input_size': list(self.preset.input_size),
            'train_input_size': [cfg.width, cfg.height],
            'training_data': data, 'steps': prior_steps + self.step, 'wall_time_s': round(self.wall_s, 1),
            'validation_metrics': metrics, 'validation_seeds': list(cfg.val_seeds),
            'loss': (f'mean over {cfg.unroll} unrolled knet-filter steps of NLL(R-Net output)'
                     + (f' + {cfg.aux_weight} * NLL(D-Net 1/4-res measurement)' if cfg.measurement_trained else '')),
            'trained_modules': [m for m in MODULES if cfg.trains(m)],
            'optimizer': (f'AdamW lr {cfg.lr} cosine (warm-up {cfg.warmup}), wd {cfg.weight_decay}, '
                          f'clip {cfg.clip}, batch {cfg.batch_size} x {self.world}'),
            'code_version': code_version(),
            'exported_at': datetime.datetime.now(datetime.timezone.utc).isoformat(timespec='seconds'),
            'command': ' '.join(self.argv),
        }

    # -- validation -----------------------------------------------------------------------------
    def validate(self) -> Dict:
        cfg = self.cfg
        t0 = time.time()
        batches = self.val_batches()
        if self.classical_ref is None:
            from dpv_sensor.core.classical import ClassicalMeasurement
            cm = ClassicalMeasurement(self.preset.d_min, self.preset.d_max, self.preset.num_planes)
            ref = evaluate_batches(None, batches, self.depths, self.device, modes=('none', 'global'), classical=cm)
            ex = ref.pop('examples')
            self.classical_ref = ref
            self._classical_examples = ex
            self._log('classical on validation seeds: ' + json.dumps(_json_safe(ref)))
        res = evaluate_batches(self.model, batches, self.depths, self.device)
        examples = res.pop('examples')
        examples += getattr(self, '_classical_examples', [])
        metrics = dict(res)
        if max(cfg.val_pose_noise) > 0:
            noisy = evaluate_batches(self.model, self.noisy_val_batches(), self.depths, self.device)
            noisy.pop('examples')
            metrics.update({f'noisy_{k}': v for k, v in noisy.items()})
        window_keys = list(metrics)
        if self.stream_validator.spec.enabled:
            try:
                metrics.update(self.stream_validator(self.model, self.device,
                                                     progress=lambda m: self._log(f'streaming validation {m}')))
            except Exception as e:      # a long run outlives a failed validation; no score means no export
                self._log(f'streaming validation FAILED ({type(e).__name__}: {e}); continuing without it')
        score = select_score(metrics, cfg.select_metric)
        entry = {'step': self.step, 'metrics': metrics, 'score': score, 'seconds': time.time() - t0}
        self.history['val'].append(entry)
        self._append_jsonl('val.jsonl', entry)
        self._log(f'validation step {self.step}: ' + ', '.join(
            f"{k}: abs_rel {v['abs_rel']:.4f} d1 {v['delta1']:.3f} nll(meas1/4 {v['nll_meas_q']:.3f} "
            f"filt1/4 {v['nll_filtered_q']:.3f} full {v['nll_full']:.3f}) conf-half {v['confident_half_ratio']:.2f}"
            for k, v in metrics.items() if k in window_keys) + f' ({entry["seconds"]:.0f} s)'
            + (f'; {cfg.select_metric} {score:.4f}' if score is not None else ''))
        d_min, d_max = self.preset.d_min, self.preset.d_max
        save_montage(examples, str(self.run_dir / f'val_montage_{self.step:07d}.png'), d_min, d_max,
                     title=f'step {self.step}, held-out seed {cfg.val_seeds[0]}, last keyframe')
        shutil.copyfile(self.run_dir / f'val_montage_{self.step:07d}.png', self.run_dir / 'val_montage_latest.png')
        plot_curves(self.history, str(self.run_dir / 'loss_curves.png'), self.classical_ref)
        if score is not None and math.isfinite(score) and (self.best is None or score < self.best):
            self.best = float(score)
            self.best_metrics = {**metrics, 'classical_same_windows': self.classical_ref}
            # the best weights also stay in the run dir (plain safetensors), whatever happens to the export
            from safetensors.torch import save_file
            tmp = self.run_dir / 'best_model.safetensors.tmp'
            save_file({k: v.detach().cpu().contiguous() for k, v in self.model.state_dict().items()}, str(tmp),
                      metadata={'step': str(self.step), 'score': str(score)})
            os.replace(tmp, self.run_dir / 'best_model.safetensors')
            try:
                export_weights(self.model, cfg.resolved_export(), self.metadata(self.best_metrics))
                self._log(f'new best {cfg.select_metric} {score:.4f}: exported {cfg.resolved_export()}')
            except Exception as e:          # never let an export problem kill a long run
                self._log(f'new best {cfg.select_metric} {score:.4f}; EXPORT FAILED ({type(e).__name__}: {e}); '
                          f'weights kept in {self.run_dir / "best_model.safetensors"}')
        return metrics

    # -- training -------------------------------------------------------------------------------
    def _all_ranks_have_grad(self, loss: torch.Tensor) -> bool:
        """Whether every rank's loss reaches a trained sub-network. A rank that skipped backward alone
        would leave the others waiting in DDP's gradient all-reduce, so the skip is collective."""
        return all_ranks(bool(loss.requires_grad), self.device, self.world)

    def train(self) -> Dict:
        from tqdm import tqdm
        cfg = self.cfg
        net = self.ddp if self.ddp is not None else self.unrolled
        self.model.train()
        start_wall = time.time()
        wall0 = self.wall_s
        loader = iter(self.loader())
        self._log(f'{cfg.preset} on {self.device}, steps in '
                  f'{"float32" if self.amp_dtype is None else str(self.amp_dtype).replace("torch.", "") + " autocast"}')
        bar = tqdm(total=cfg.steps, initial=self.step, disable=not self.is_main or self.quiet, dynamic_ncols=True,
                   mininterval=1.0 if sys.stderr.isatty() else 30.0, desc=f'train {cfg.preset}')
        last_log = []
        try:
            if self.is_main and self.step == 0 and not self.history['val']:
                self.validate()
            while self.step < cfg.steps:
                if cfg.max_minutes and (time.time() - start_wall) > cfg.max_minutes * 60:
                    self._log(f'--max-minutes {cfg.max_minutes} reached')
                    break
                t0 = time.time()
                batch = _to_device(next(loader), self.device)
                t1 = time.time()
                lr = _lr_at(cfg, self.step)
                for g in self.optimizer.param_groups:
                    g['lr'] = lr
                with torch.autocast(device_type=self.device.type, dtype=self.amp_dtype or torch.float32,
                                    enabled=self.amp_dtype is not None):
                    loss, stats = net(batch)
                self.optimizer.zero_grad(set_to_none=True)
                if self._all_ranks_have_grad(loss):
                    self.scaler.scale(loss).backward()
                    self.scaler.unscale_(self.optimizer)
                    gnorm = torch.nn.utils.clip_grad_norm_(self.model.parameters(), cfg.clip)
                    if torch.isfinite(gnorm):
                        self.scaler.step(self.optimizer)
                    else:
                        self._log(f'step {self.step}: non-finite gradient, update skipped')
                    self.scaler.update()
                else:   # only frozen sub-networks shaped this loss (here or on another rank), e.g.
                    # --train-modules knet with every unrolled step a filter reset
                    gnorm = torch.zeros(())
                    self._log(f'step {self.step}: the loss reaches no trained sub-network '
                              f'({stats.get("resets", 0)} filter resets), update skipped')
                self.step += 1
                self.samples_seen += cfg.batch_size
                t2 = time.time()
                self.wall_s = wall0 + (t2 - start_wall)
                stats.update(step=self.step, lr=lr, grad_norm=float(gnorm), t_data=t1 - t0, t_step=t2 - t1)
                last_log.append(stats)
                bar.update(1)
                bar.set_postfix(loss=f"{stats['loss']:.3f}", nll=f"{stats['nll_full']:.3f}")
                if self.step % cfg.log_every == 0 or self.step == cfg.steps:
                    row = {k: float(np.mean([s[k] for s in last_log])) for k in last_log[0] if k != 'step'}
                    row['step'] = self.step
                    row['wall_s'] = self.wall_s
                    self.history['train'].append(row)
                    self._append_jsonl('train.jsonl', row)
                    self._log(f"step {self.step} loss {row['loss']:.4f} nll_full {row['nll_full']:.4f} "
                              f"nll_q {row['nll_meas_q']:.4f} |g| {row['grad_norm']:.2f} lr {lr:.2e} "
                              f"{row['t_step']:.2f}+{row['t_data']:.2f} s/step")
                    last_log = []
                    if self.is_main:
                        plot_curves(self.history, str(self.run_dir / 'loss_curves.png'), self.classical_ref)
                if self.step % cfg.val_every == 0 or self.step == cfg.steps:
                    if self.is_main:
                        self.validate()
                    if self.world > 1:
                        torch.distributed.barrier()
                if self.step % cfg.ckpt_every == 0:
                    self.save()
        except KeyboardInterrupt:
            self._log('interrupted; writing a checkpoint')
        finally:
            bar.close()
            self.save()
            if self.is_main:
                plot_curves(self.history, str(self.run_dir / 'loss_curves.png'), self.classical_ref)
        return {'step': self.step, 'best': self.best, 'history': self.history}


def train(cfg: TrainConfig, resume: bool = False, quiet: bool = False, argv: Optional[List[str]] = None) -> Dict:
    """Build a :class:`Trainer` and run it; returns {'step', 'best', 'history'}."""
    t = Trainer(cfg, resume=resume, quiet=quiet, argv=argv)
    try:
        return t.train()
    finally:
        if t.world > 1 and torch.distributed.is_initialized():
            torch.distributed.destroy_process_group()
