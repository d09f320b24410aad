"""The window validation: held-out synthetic seeds run through the unrolled pipeline and scored.

Validation (every ``val_every`` steps = one "epoch"; rank 0) runs held-out synthetic seeds (0..99,
never produced by the training stream) through the same unrolled pipeline in the filter modes
none / global / knet and reports abs_rel, delta1, the confident-half ratio and the NLL of the GT
before the filter (D-Net measurement) and after it; the classical ZNCC model is scored once on the
same windows for comparison. The streaming validation through the product's Estimator lives in
:mod:`.stream_validation`.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Dict, List, Sequence as Seq, Tuple

import numpy as np
import torch
import torch.nn.functional as F

from dpv_sensor import params as _params
from dpv_sensor.core import dpv as dpvops
from dpv_sensor.core import geometry
from dpv_sensor.training.config import FILTER_MODES
from dpv_sensor.training.dataset import TRAIN_SEED_BASE, VAL_SEEDS, WindowLayout, sample_from_sequence
from dpv_sensor.training.unrolled import batch_to_device, filter_steps, measure_steps, quarter_gt

__all__ = ['render_validation_batches', 'corrupt_validation_batches', 'evaluate_batches']


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
    was_training = model.training if model is not None else False
    if model is not None:
        model.eval()
    sources = []
    if model is not None:
        sources.append(('net', model))
    if classical is not None:
        sources.append(('classical', classical))
    opts = _ScoreOptions(depths_d, device, readout, confidence, confidence_ratio, keep_last)
    results: Dict = {}
    examples: List[Dict] = []
    for name, src in sources:
        scores = _score_source(name, src, batches, _source_modes(name, modes), opts, examples)
        for mode, mode_scores in scores.items():
            results[f'{name}_{mode}'] = mode_scores.entry(curves)
    if model is not None and was_training:
        model.train()
    results['examples'] = examples
    return results


@dataclasses.dataclass
class _ScoreOptions:
    """How :func:`evaluate_batches` turns DPVs into scored depth and confidence."""
    depths_d: torch.Tensor
    device: Any
    readout: str
    confidence: str
    confidence_ratio: float
    keep_last: bool


@dataclasses.dataclass
class _ModeScores:
    """What one (source, filter mode) collects over the validation frames."""
    acc: Any                                # MetricAccumulator
    nll_meas_q: List[float] = dataclasses.field(default_factory=list)
    nll_filtered_q: List[float] = dataclasses.field(default_factory=list)
    nll_full: List[float] = dataclasses.field(default_factory=list)

    def add_step(self, m: Dict, r: Dict, readout: str, opts: _ScoreOptions) -> Tuple[torch.Tensor, torch.Tensor]:
        """Score one unrolled step (measurement ``m``, filter result ``r``); returns its depth and confidence."""
        depths_d = opts.depths_d
        gt = m['gt']
        gq = quarter_gt(gt, m['logp_q'].shape[-2:])
        self.nll_meas_q.append(float(dpvops.nll(m['logp_q'].float(), depths_d, gq)))
        self.nll_filtered_q.append(float(dpvops.nll(r['filtered_q'].float(), depths_d, gq)))
        if 'logp_full' in r:
            lp = r['logp_full'].float()
            self.nll_full.append(float(dpvops.nll(lp, depths_d, gt)))
            depth = dpvops.depth_estimate(lp, depths_d, readout)
            conf = dpvops.published_confidence(lp, depths_d, depth, opts.confidence, opts.confidence_ratio)
        else:                                   # classical: upsample the quarter-res maps
            lq = r['filtered_q'].float()
            H, W = gt.shape[-2:]
            dq = dpvops.depth_estimate(lq, depths_d, readout)
            depth = _upsample_map(dq, (H, W))
            conf = _upsample_map(dpvops.published_confidence(lq, depths_d, dq, opts.confidence,
                                                             opts.confidence_ratio), (H, W))
        for b in range(gt.shape[0]):
            self.acc.add(_np(depth[b]), _np(gt[b]), confidence=_np(conf[b]))
        return depth, conf

    def entry(self, curves: bool) -> Dict:
        """The validation entry of this (source, mode): depth and confidence metrics, then the mean NLLs."""
        s = self.acc.summary()
        fm = s['metric']['frame_mean']
        conf = s.get('confidence', {})
        entry = {'abs_rel': fm['abs_rel'], 'delta1': fm['delta1'], 'rmse': fm['rmse'],
                 'confident_half_ratio': conf.get('confident_half_ratio_frame_mean', float('nan')),
                 'confident_half_ratio_pooled': conf.get('confident_half_ratio_pooled', float('nan')),
                 'ause': conf.get('ause_frame_mean', float('nan')),
                 'aurg': conf.get('aurg_of_mean_curve', float('nan')),
                 'frames': s['num_frames']}
        if curves:
            entry['sparsification_curves'] = self.acc.mean_curves()
        for k, v in (('nll_meas_q', self.nll_meas_q), ('nll_filtered_q', self.nll_filtered_q),
                     ('nll_full', self.nll_full)):
            entry[k] = float(np.mean(v)) if v else float('nan')
        return entry


def _source_modes(name: str, modes: Seq[str]) -> List[str]:
    """The filter modes a source is scored in (the classical model has no K-Net)."""
    return [m for m in modes if not (name == 'classical' and m == 'knet')]


def _score_source(name: str, src, batches: List[Dict[str, torch.Tensor]], modes: Seq[str], opts: _ScoreOptions,
                  examples: List[Dict]) -> Dict[str, _ModeScores]:
    """Run one source ('net' or 'classical') over the batches in every mode; appends the last step of the first
    batch per mode to ``examples`` (with ``keep_last``)."""
    from dpv_sensor.evaluation.metrics import MetricAccumulator
    readout = dpvops.resolve_readout(opts.readout, learned=name == 'net')
    scores = {mode: _ModeScores(MetricAccumulator()) for mode in modes}
    for bi, batch in enumerate(batches):
        batch = batch_to_device(batch, opts.device)
        meas = measure_steps(src, batch) if name == 'net' else _classical_steps(src, batch)
        for mode in modes:
            if name == 'net':
                res = filter_steps(src, meas, opts.depths_d, mode)
            else:
                res = filter_steps(_NoKnet(), meas, opts.depths_d, mode, refine=False)
            for j, (m, r) in enumerate(zip(meas, res)):
                depth, conf = scores[mode].add_step(m, r, readout, opts)
                if opts.keep_last and bi == 0 and j == len(meas) - 1:
                    examples.append(dict(source=name, mode=mode, image=_np(m['image'][0]).transpose(1, 2, 0),
                                         gt=_np(m['gt'][0]), depth=_np(depth[0]), conf=_np(conf[0])))
    return scores


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
