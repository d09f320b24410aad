"""Streaming validation: held-out rendered sequences pushed through the product's ``Estimator``.

The trainer's window validation (:func:`dpv_sensor.training.validation.evaluate_batches`) unrolls the filter
over a few keyframes at training size. The node instead streams every frame of a sequence through
:class:`dpv_sensor.stream.estimator.Estimator`: keyframe selection, causal five-frame windows at 320x256,
15-20 keyframes of K-Net filtering, the depth readout and confidence it publishes. A K-Net trained over
long unrolls can get better on streams while the short windows show no change (this happened: see
README, "Training and evaluation"), so exports chosen by the window validation can be the wrong ones.

:class:`StreamValidator` scores a model on rendered held-out seeds the way the node would use it, with
the sequences' GT poses and (optionally) with odometry-like poses (``pose_noise`` = relative
translation noise per step, rotation noise in degrees per step; seeded per sequence, the same at every
validation). It returns one entry per (pose source, filter mode):

    ``stream_net_<mode>`` (GT poses) and ``stream_noisy_net_<mode>`` (noisy poses):
    ``{abs_rel, delta1, ms_abs_rel, confident_half_ratio, confident_half_ratio_pooled, frames, per_seed}``

``abs_rel``, ``delta1`` and ``ms_abs_rel`` (median-scaled) are means over the seeds of each sequence's
frame mean; ``per_seed`` lists the abs_rel of each seed. It reads and writes no files and never touches
ROS; the estimator runs with the node's defaults but without the pose-refinement window
(``pose_refinement: off``), on the caller's device: it scores the networks on the poses given, and a training
machine needs no gtsam.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence as Seq, Tuple

import numpy as np

from dpv_sensor.training.dataset import check_heldout_seeds
from dpv_sensor import params as P

__all__ = ['StreamValidationSpec', 'StreamValidator', 'stream_metric_key']

STREAM_PREFIX = 'stream_'


def stream_metric_key(mode: str, noisy: bool) -> str:
    """The metrics key of one streaming entry, e.g. ``stream_noisy_net_knet``."""
    return f'{STREAM_PREFIX}{"noisy_" if noisy else ""}net_{mode}'


@dataclass(frozen=True)
class StreamValidationSpec:
    """Which sequences are streamed and how.

    seeds: rendered held-out seeds (must lie in ``VAL_SEEDS``); frames: frames per sequence (30 Hz);
    size: (width, height) rendered (the estimator resizes to its processing size as the node does);
    pose_noise: (relative translation, degrees) per step for the noisy-pose pass, (0, 0) = GT poses only;
    modes: filter modes scored; world_scale: each sequence seen in a world that many times larger
    (:meth:`~dpv_sensor.data.sequence.Sequence.world_scaled`: depths and translations, the same images).
    """
    seeds: Tuple[int, ...] = ()
    frames: int = 60
    size: Tuple[int, int] = (320, 240)
    pose_noise: Tuple[float, float] = (0.03, 0.5)
    modes: Tuple[str, ...] = ('knet',)
    world_scale: float = 1.0

    @property
    def enabled(self) -> bool:
        return len(self.seeds) > 0

    @property
    def noisy(self) -> bool:
        return max(self.pose_noise) > 0

    def check(self) -> 'StreamValidationSpec':
        from dpv_sensor.stream.estimator import FILTER_MODES
        check_heldout_seeds(self.seeds, 'streaming validation seed')
        if self.enabled and self.frames < 10:
            raise ValueError(f'streaming validation needs at least 10 frames per sequence, got {self.frames}')
        if len(self.size) != 2 or min(self.size) < 32:
            raise ValueError(f'streaming validation size must be (width, height) >= 32, got {self.size}')
        if len(self.pose_noise) != 2 or min(self.pose_noise) < 0:
            raise ValueError(f'streaming validation pose noise must be (relative translation, degrees) >= 0, '
                             f'got {self.pose_noise}')
        if not self.world_scale > 0:
            raise ValueError(f'streaming validation world scale must be positive, got {self.world_scale}')
        unknown = [m for m in self.modes if m not in FILTER_MODES]
        if unknown or not self.modes:
            raise ValueError(f'streaming validation modes {list(self.modes)}: choose from {FILTER_MODES}')
        return self


class StreamValidator:
    """Scores a ``DPVNet`` by streaming the spec's sequences through the estimator (see module docstring).

    The sequences are rendered once (lazily: frames are drawn when the estimator asks for them) and kept.
    Calling the validator puts the model in eval mode and returns it to the mode it was in.
    """

    def __init__(self, spec: StreamValidationSpec):
        self.spec = spec.check()
        self._sequences: Optional[List] = None

    def sequences(self) -> List:
        if self._sequences is None:
            from dpv_sensor.data.synthetic import render_sequence
            w, h = self.spec.size
            self._sequences = [render_sequence(s, self.spec.frames, width=w, height=h, lazy=True)
                               .world_scaled(self.spec.world_scale) for s in self.spec.seeds]
        return self._sequences

    def pose_sources(self) -> Tuple[str, ...]:
        return ('gt', 'noisy') if self.spec.noisy else ('gt',)

    def __call__(self, model, device=P.default('device'), progress=None) -> Dict[str, Dict]:
        """``{stream_[noisy_]net_<mode>: metrics}`` for ``model`` on ``device`` (see module docstring).

        progress: an optional callable(str) told the result of each (pose source, mode) pass over the
        sequences (the trainer logs through it). The estimator takes the depth planes from the model, so any
        preset works; the paper preset wants ``device='cuda'``."""
        from dpv_sensor.evaluation.offline import EvalOptions, evaluate_sequence
        if not self.spec.enabled:
            return {}
        was_training = model.training
        out: Dict[str, Dict] = {}
        try:
            for src in self.pose_sources():
                for mode in self.spec.modes:
                    t0 = time.time()
                    rows = []
                    for seed, seq in zip(self.spec.seeds, self.sequences()):
                        opts = EvalOptions(seed=seed, progress=False, pose_noise=tuple(self.spec.pose_noise))
                        summ = evaluate_sequence(seq, {'filter_mode': mode, 'pose_source': src,
                                                       'device': str(device), 'pose_refinement': 'off',
                                                       'depth_anchors': 'off'},   # the anchors need the window
                                                 options=opts, model=model)
                        rows.append(_summary_row(summ))
                    key = stream_metric_key(mode, noisy=src == 'noisy')
                    out[key] = _mean_rows(rows)
                    out[key]['seconds'] = round(time.time() - t0, 1)
                    if progress is not None:
                        progress(f'{key}: abs_rel {out[key]["abs_rel"]:.4f} over {len(rows)} sequences '
                                 f'({out[key]["seconds"]:.0f} s)')
        finally:
            model.train(was_training)
        return out


def _summary_row(summary: Dict) -> Dict:
    fm = summary['metric']['frame_mean']
    conf = summary.get('confidence', {}) or {}
    return {'abs_rel': float(fm['abs_rel']), 'delta1': float(fm['delta1']),
            'ms_abs_rel': float(summary['median_scaled']['frame_mean']['abs_rel']),
            'confident_half_ratio': float(conf.get('confident_half_ratio_frame_mean', float('nan'))),
            'confident_half_ratio_pooled': float(conf.get('confident_half_ratio_pooled', float('nan'))),
            'frames': int(summary['num_frames'])}


def _mean_rows(rows: Seq[Dict]) -> Dict:
    out: Dict = {}
    for k in ('abs_rel', 'delta1', 'ms_abs_rel', 'confident_half_ratio', 'confident_half_ratio_pooled'):
        vals = np.array([r[k] for r in rows], np.float64)
        out[k] = float(np.nanmean(vals)) if np.isfinite(vals).any() else float('nan')
    out['frames'] = int(sum(r['frames'] for r in rows))
    out['per_seed'] = [round(r['abs_rel'], 4) for r in rows]
    return out

