"""Adapting the networks to one recording without depth labels: the loop behind the ``adapt`` tool.

The recording (images, intrinsics, camera poses; :mod:`dpv_sensor.data.recording`) is resized to the node's
processing size and cut into keyframes with the node's own keyframe rule (:class:`~dpv_sensor.stream.keyframes.
KeyframeSelector` at its defaults). About ``holdout`` of its keyframes are held out, in blocks spread over the
recording (:func:`spread_keyframes`; a recording too short for blocks is refused), or with ``holdout_layout='end'``
the last ``holdout`` share of its frames (:func:`split_keyframes`); training samples are runs of ``unroll + window - 1``
consecutive keyframes of one part between the blocks (played forwards or backwards), laid out in five-frame windows
as the trainer lays them (:func:`dpv_sensor.training.dataset.sample_from_sequence`), and go through the
trainer's unrolled stream (:func:`dpv_sensor.training.unrolled.measure_steps` and ``filter_steps``: D-Net, the K-Net
filter, R-Net). Each unrolled step's depth warps the window's sources into the reference
(:mod:`.self_supervised`); the loss per batch is::

    L = photometric * mean_j [photo(R-Net output_j) + aux * photo(D-Net 1/4-res measurement_j)]
        + evidence * mean_j [ev(R-Net output_j) + aux * ev(D-Net 1/4-res measurement_j)]
        + penalty * ||theta - theta_base||^2  +  distill * mean_pixels w * KL(p_base || p)

``w`` is 1, or with ``distill_pixels='confident'`` the base network's published confidence mapped by
:func:`~dpv_sensor.training.self_supervised.confidence_tie_weight` (0 below ``distill_threshold``, 1 at 1): what the
base network was sure of stays, what it guessed is left to the photometry. ``photo`` is the auto-masked
photometric reprojection error of the DPV's depth (SSIM + L1, per-pixel minimum over the sources); ``ev``
the negative log photometric evidence of the whole DPV on its quarter-resolution grid
(:func:`~dpv_sensor.training.self_supervised.photometric_evidence`: every plane's patch error from the plane sweep,
likelihood ``exp(-e / sigma)``). With ``supervised`` the loss is the trainer's instead
(:func:`dpv_sensor.training.unrolled.run_unrolled`: NLL of the recording's depth), and the depth is read.

**Held-out scores**: per held-out run (the runs of :func:`spread_keyframes` or :func:`split_keyframes`, at most
``max_holdout_runs``), scored alike for the base and the adapted weights:

- ``anchors`` (the default judge, ``judge``): the σ-weighted mean absolute log-depth error of the R-Net output's
  depth (the node's readout) at metric anchors of the held-out keyframes, triangulated with the recording's poses
  from frames never trained on (:mod:`dpv_sensor.training.anchor_judge`; no training keyframe). A run with fewer than
  ``min_anchors`` anchors is not judged; with fewer judged runs than the sign-flip test needs at ``significance``
  the run is refused before training, saying why (a camera turning in place, blank walls).
- ``photometric``: the mean photometric reprojection error of the same depth over every pixel of the run, no
  auto-mask, a pixel sent out of every source counting with the unwarped sources' error
  (:func:`dpv_sensor.training.self_supervised.score_error`), so both weights are scored on exactly the same
  pixels. Beside the anchors' judge it may veto: adapted weights whose photometric score is worse by the same test
  are not written. With ``judge='photometric'`` it decides alone and the anchors' score is reported beside it.
- with ``supervised``: the NLL of the held-out depth decides.

The adapted weights are kept only when the deciding score's runs show the gain (a one-sided sign-flip test,
:mod:`dpv_sensor.training.heldout_decision`); :class:`AdaptResult` says which. ``anchor_loss`` > 0 adds a sparse
depth loss at the training keyframes' own anchors (:func:`~dpv_sensor.training.anchor_judge.anchor_loss`) to the
photometric terms.

**Time**: ``minutes`` caps the whole run (loading, both held-out scores, training): training stops when the
time left would not cover one more step and the adapted weights' held-out score (timed on the base weights).
Everything is seeded (``seed``): the same recording and settings give the same weights, bit for bit, when the run
is cut by ``max_steps`` rather than by the clock.
"""
from __future__ import annotations

import dataclasses
import math
import time
from typing import Callable, Dict, List, Optional, Sequence as Seq, Tuple

import numpy as np
import torch

from dpv_sensor import params as P
from dpv_sensor.core import dpv as dpvops
from dpv_sensor.training.adapt_poses import POSE_SOURCES, node_keyframe_poses
from dpv_sensor.training.anchor_judge import JUDGES, AnchorScore, JudgeConfig, anchor_loss, frame_anchors
from dpv_sensor.training.config import MODULES
from dpv_sensor.training.dataset import WindowLayout, sample_from_sequence
from dpv_sensor.training.heldout_decision import HeldOutVerdict, judge, runs_needed, veto
from dpv_sensor.training.self_supervised import (confidence_tie_weight, distillation, downsample_image, masked_mean,
                                                 parameter_penalty, photometric_evidence, plane_errors,
                                                 reprojection_error, score_error)
from dpv_sensor.training.unrolled import filter_steps, measure_steps, run_unrolled

__all__ = ['AdaptConfig', 'AdaptResult', 'Adapter', 'select_keyframes', 'split_keyframes', 'spread_keyframes',
           'DEFAULT_MINUTES', 'HOLDOUT_LAYOUTS', 'DISTILL_PIXELS', 'LOSS_DESCRIPTION']

# The default time cap of a whole run: a 700-image 640x480 recording at the 320x256 processing size fits the
# 20 minutes of a 2-core CPU with this (loading and resizing, two held-out scores, the report).
DEFAULT_MINUTES = 18.0
HOLDOUT_LAYOUTS = ('end', 'spread')
DISTILL_PIXELS = ('all', 'confident')

LOSS_DESCRIPTION = ('mean over the unrolled knet-filter steps of: photometric x the auto-masked photometric '
                    "reprojection error (0.85 SSIM + 0.15 L1, per-pixel minimum over the window's sources) of the "
                    "R-Net output's depth + evidence x the negative log photometric evidence of its DPV (plane sweep "
                    'of 3x3 patches, likelihood exp(-error / sigma)), each + aux x the same for the D-Net 1/4-res '
                    'measurement; + penalty x ||theta - theta_base||^2 + distill x KL(base DPV || adapted DPV) '
                    "(with distill_pixels 'confident': per pixel, weighted by the base network's confidence above "
                    'distill_threshold)')


@dataclasses.dataclass
class AdaptConfig:
    """Settings of one adaptation run (stored in the adapted weights' metadata)."""
    width: int = P.default('processing_width')     # the node's processing size: what the nets will see
    height: int = P.default('processing_height')
    minutes: float = DEFAULT_MINUTES                # the whole run's time cap
    max_steps: int = 0                              # 0: as many as ``minutes`` allows
    lr: float = 1e-3
    warmup: int = 10
    min_lr_ratio: float = 0.05                      # the cosine decay's end (see Adapter.learning_rate)
    clip: float = 1.0
    batch_size: int = 1
    unroll: int = 2                                 # filter steps per sample
    window: int = P.default('window_size')
    ref_position: str = 'center'                    # the node's default window (window_mode: centered)
    holdout: float = 0.2                            # share held out: the last frames, or keyframes in blocks
    holdout_layout: str = 'spread'                  # 'spread': blocks across the recording; 'end': the last frames
    holdout_blocks: int = 4                         # 'spread': at most this many held-out blocks
    max_holdout_runs: int = 16                      # held-out runs scored (evenly spread over the slice)
    significance: float = 0.05                      # written when better with a sign-flip p at most this (1: mean)
    train_modules: Tuple[str, ...] = ()             # sub-networks adapted (see training.config.MODULES); () = all
    photometric: float = 1.0                        # weight of the photometric reprojection term
    evidence: float = 1.0                           # weight of the plane sweep's photometric evidence term
    sigma: float = 0.05                             # its photometric error scale
    aux: float = 0.5                                # weight of the 1/4-res measurement's terms
    penalty: float = 1.0                            # L2-SP weight
    distill: float = 1.0                            # weight of KL(base DPV || adapted DPV) (a second forward)
    distill_pixels: str = 'confident'               # only where the base is sure (confidence_tie_weight); or 'all'
    distill_threshold: float = 0.5                  # 'confident': the base confidence where the tie starts
    readout: str = 'relative'                       # the depth the photometric loss warps with (the node's)
    automask: bool = True
    supervised: bool = False                        # the trainer's NLL on the recording's depth instead
    poses: str = 'odometry'                         # as recorded; 'window': the node's refined keyframe poses
    judge: str = 'anchors'                          # what decides (training.anchor_judge.JUDGES; supervised: nll)
    anchor_loss: float = 0.0                        # weight of the sparse loss on training keyframes' anchors
    seed: int = 0

    def check(self) -> 'AdaptConfig':
        if self.width % 4 or self.height % 4 or min(self.width, self.height) < 32:
            raise ValueError(f'processing size must be multiples of 4 and >= 32, got {self.width}x{self.height}')
        if not 0.05 <= self.holdout <= 0.5:
            raise ValueError(f'holdout must lie in [0.05, 0.5], got {self.holdout}')
        if self.holdout_layout not in HOLDOUT_LAYOUTS or self.holdout_blocks < 1:
            raise ValueError(f'holdout_layout must be one of {HOLDOUT_LAYOUTS} and holdout_blocks >= 1, got '
                             f'{self.holdout_layout!r}, {self.holdout_blocks}')
        if not 0 < self.significance <= 1:
            raise ValueError(f'significance must lie in (0, 1], got {self.significance}')
        if self.minutes <= 0 or self.lr <= 0 or self.unroll < 1 or self.batch_size < 1 or self.max_steps < 0:
            raise ValueError('minutes and lr must be > 0, unroll and batch_size >= 1, max_steps >= 0')
        unknown = set(self.train_modules) - set(MODULES)
        if unknown:
            raise ValueError(f'train_modules: unknown {sorted(unknown)}; choose from {MODULES}')
        if self.readout not in dpvops.READOUTS:
            raise ValueError(f'readout must be one of {dpvops.READOUTS}, got {self.readout!r}')
        if min(self.aux, self.penalty, self.distill, self.photometric, self.evidence) < 0 or self.sigma <= 0:
            raise ValueError('loss weights must be >= 0 and sigma > 0')
        if self.distill_pixels not in DISTILL_PIXELS or not 0 <= self.distill_threshold < 1:
            raise ValueError(f'distill_pixels must be one of {DISTILL_PIXELS} and distill_threshold in [0, 1), got '
                             f'{self.distill_pixels!r}, {self.distill_threshold}')
        if self.poses not in POSE_SOURCES:
            raise ValueError(f'poses must be one of {POSE_SOURCES}, got {self.poses!r}')
        if self.judge not in JUDGES or self.anchor_loss < 0:
            raise ValueError(f'judge must be one of {JUDGES} and anchor_loss >= 0, got {self.judge!r}, '
                             f'{self.anchor_loss}')
        if self.photometric == 0 and self.evidence == 0 and not self.supervised:
            raise ValueError('photometric and evidence weights are both 0: nothing to adapt with')
        return self

    def layout(self) -> WindowLayout:
        return WindowLayout(steps=self.unroll, window=self.window, ref_position=self.ref_position)

    def trains(self, module: str) -> bool:
        return not self.train_modules or module in self.train_modules

    def to_json(self) -> Dict:
        d = dataclasses.asdict(self)
        d['train_modules'] = list(self.train_modules)
        return d


@dataclasses.dataclass
class AdaptResult:
    """What a run did: steps, the held-out scores (lower is better), why it stopped, its time, the training history
    and a few held-out examples (image, depth and confidence before and after) for the report."""
    steps: int
    base_score: float
    adapted_score: float
    score_kind: str
    stop_reason: str
    seconds: Dict[str, float]
    history: List[Dict]
    keyframes: Dict[str, int]
    examples: List[Dict]
    verdict: HeldOutVerdict                         # the deciding per-run comparison (training.heldout_decision)
    beside: Dict[str, Dict] = dataclasses.field(default_factory=dict)   # the other scores: base, adapted, verdict
    anchors: Optional[Dict] = None                  # the judge's anchors: per held-out run, runs judged
    refused: Optional[str] = None                   # why nothing was trained (the judge cannot judge)
    runs: Optional[Dict[str, List[float]]] = None   # the deciding score of each held-out run: base, adapted

    @property
    def improved(self) -> bool:
        return self.steps > 0 and self.verdict.better and self.refused is None


def split_keyframes(kfs: List[int], frames: int, holdout: float, layout: WindowLayout
                    ) -> Tuple[int, List[int], List[int], List[List[int]]]:
    """(split frame, training keyframes, held-out keyframes, held-out runs) of a recording's keyframes ``kfs``.

    The frames from the split on are held out: the last ``holdout`` share, or where that holds fewer than the
    ``M - ref_slot`` keyframes one run needs from its first reference on (4 for the default M = 6), the last that
    many keyframes, as long as the training part keeps M. Training samples are runs of M training keyframes. The
    held-out runs are every M-keyframe run whose references are all held out, so every held-out keyframe that can be
    a reference is scored as one: the first runs borrow their first ``ref_slot`` sources from the training part (their
    images, never a scored pixel). ValueError names the part that is too short."""
    M, r = layout.num_keyframes, layout.ref_slot
    need = M - r
    split = int(round(frames * (1.0 - holdout)))
    if sum(k >= split for k in kfs) < need and len(kfs) >= M + need:
        split = kfs[-need]
    train = [k for k in kfs if k < split]
    held = [k for k in kfs if k >= split]
    rule = (f"(the node picks one every {P.default('keyframe_translation')} m, {P.default('keyframe_rotation_deg')} "
            f"deg or {P.default('keyframe_max_interval')} frames)")
    if len(train) < M:
        raise ValueError(f'the recording is too short: its training part has {len(train)} keyframes {rule}, {M} are '
                         f'needed ({M + need} in all)')
    if len(held) < need:
        raise ValueError(f'the recording is too short: its held-out slice has {len(held)} keyframes {rule}, {need} '
                         f'are needed ({M + need} in all)')
    runs = [kfs[s:s + M] for s in range(len(train) - r, len(kfs) - M + 1)]
    return split, train, held, runs


def spread_keyframes(kfs: List[int], holdout: float, layout: WindowLayout, blocks: int
                     ) -> Tuple[List[List[int]], List[int], List[List[int]]]:
    """(training segments, held-out keyframes, held-out runs) with the held-out keyframes in up to ``blocks`` blocks
    spread evenly over the recording, about ``holdout`` of its keyframes in all, instead of its last part: the score
    then stands for the whole place the recording covers, not only where it ends.

    Each block holds at least the ``unroll`` references of one run; every training segment around the blocks keeps
    at least M keyframes (the first and the last may be empty), so no keyframe is left out of both parts, and fewer
    blocks are used where that does not fit. A training sample is M consecutive keyframes of one segment, so no
    held-out image is ever trained on. The held-out runs are every M-keyframe run whose references are all in one
    block; their other keyframes may come from the segments around it (their images, never a scored pixel).
    ValueError when not even one block fits."""
    M, r, n = layout.num_keyframes, layout.ref_slot, len(kfs)
    steps = M - layout.window + 1                     # the references of one run
    for nb in range(max(1, int(blocks)), 0, -1):
        size = max(steps, int(round(holdout * n / nb)))
        # block b is centred at (b + 1/2) / nb of the keyframes, its first held-out keyframe at start[b]
        starts = [min(n - size, max(0, int(round((b + 0.5) * n / nb - size / 2.0)))) for b in range(nb)]
        bounds = [0] + [x for st in starts for x in (st, st + size)] + [n]
        segments = [list(range(bounds[2 * i], bounds[2 * i + 1])) for i in range(nb + 1)]
        if any(0 < len(sg) < M for sg in segments) or any(len(sg) < M for sg in segments[1:-1]):
            continue                                  # a segment too short to train on would be wasted
        held_idx = [i for st in starts for i in range(st, st + size)]
        runs = [list(range(s0, s0 + M)) for st in starts for s0 in range(st - r, st + size - steps - r + 1)
                if s0 >= 0 and s0 + M <= n]
        if not runs:
            continue
        return ([[kfs[i] for i in sg] for sg in segments if sg], [kfs[i] for i in held_idx],
                [[kfs[i] for i in run] for run in runs])
    raise ValueError(f'the recording is too short for a spread held-out part: {n} keyframes, at least '
                     f'{2 * M + steps} are needed (two training segments of {M} and a block of {steps})')


def select_keyframes(poses: Seq[np.ndarray]) -> List[int]:
    """Frame indices the node's keyframe rule picks along ``poses`` (its defaults: baseline, rotation, interval)."""
    from dpv_sensor.stream.keyframes import KeyframeSelector
    sel = KeyframeSelector(translation=P.default('keyframe_translation'),
                           rotation_deg=P.default('keyframe_rotation_deg'),
                           max_interval=P.default('keyframe_max_interval'))
    return [i for i, T in enumerate(poses) if sel.decide(np.asarray(T, np.float64)).is_keyframe]


def _collate(samples: List[Dict[str, torch.Tensor]]) -> Dict[str, torch.Tensor]:
    return {k: torch.stack([s[k] for s in samples]) for k in samples[0]}


class Adapter:
    """One adaptation run of ``model`` (a DPVNet, adapted in place) on ``sequence`` (resized to the processing size;
    see the module docstring)."""

    def __init__(self, cfg: AdaptConfig, model, sequence, log: Optional[Callable[[str], None]] = None,
                 progress: bool = False):
        self.cfg = cfg.check()
        self.log = log or (lambda _m: None)
        self.model = model
        self.pose_stats: Optional[Dict] = None
        kfs = None
        if cfg.poses == 'window':
            t0 = time.time()
            node = node_keyframe_poses(sequence, model, cfg.width, cfg.height, progress=progress)
            sequence, kfs = sequence.with_poses(node.poses), node.keyframes
            self.pose_stats = dict(node.stats, seconds=round(time.time() - t0, 1))
            ch = node.stats['step_rotation_change_deg']
            self.log(f"poses: the node's window refined {node.stats['refined']} of {node.stats['keyframes']} "
                     f"keyframes (a keyframe step's rotation moved {ch['median']:.3f} deg in the median, "
                     f"{ch['max']:.3f} at most; {self.pose_stats['seconds']:.0f} s)")
        self.seq = sequence
        self.depths_d = model.depth_planes(torch.float32)
        self.base = {k: v.detach().clone() for k, v in model.named_parameters()}
        self.base_model = None
        if cfg.distill > 0:
            import copy
            self.base_model = copy.deepcopy(model).eval().requires_grad_(False)
        frames = len(sequence)
        if kfs is None:
            kfs = select_keyframes([sequence.pose(i) for i in range(frames)])
        M = cfg.layout().num_keyframes
        self.holdout_layout = cfg.holdout_layout
        if self.holdout_layout == 'spread':
            try:
                segments, self.held_kf, runs = spread_keyframes(kfs, cfg.holdout, cfg.layout(), cfg.holdout_blocks)
                self.train_kf = [k for sg in segments for k in sg]
                self.split = None
            except ValueError as exc:
                # a score of the frames right after the training part does not stand for the place: on a recording
                # this short the adapted weights are not judged at all unless 'end' is asked for
                raise ValueError(f'{exc}: too short to judge the adapted weights on more than its last frames; '
                                 "record a longer stretch of the place, or hold out its last frames with "
                                 "holdout_layout 'end' (--holdout-layout end)") from None
        if self.holdout_layout == 'end':
            self.split, self.train_kf, self.held_kf, runs = split_keyframes(kfs, frames, cfg.holdout, cfg.layout())
            segments = [self.train_kf]
        # every training sample: M consecutive keyframes of one training segment
        self.train_runs = [sg[s:s + M] for sg in segments for s in range(len(sg) - M + 1)]
        if len(runs) > cfg.max_holdout_runs:
            runs = [runs[int(i)] for i in np.linspace(0, len(runs) - 1, cfg.max_holdout_runs).round()]
        self.held_runs = runs
        self.judge_config = JudgeConfig()
        self.held_anchors: Dict[int, object] = {}
        self.train_anchors: Dict[int, object] = {}
        if not cfg.supervised:           # the anchors' score: the judge, or reported beside the photometric judge
            t0 = time.time()
            # from frames never trained on: anything but a training keyframe
            trained = set(self.train_kf)
            self.held_anchors = frame_anchors(sequence, self.held_kf, lambda f: f not in trained, self.judge_config)
            counts = [len(a) for a in self.held_anchors.values()]
            self.log(f'anchors of the held-out keyframes: {sum(counts)} ({int(np.median(counts)) if counts else 0} a '
                     f'keyframe in the median; {time.time() - t0:.0f} s)')
        if not cfg.supervised and cfg.anchor_loss > 0:
            # from frames outside the held-out parts
            held = [range(a, b + 1) for a, b in self.held_frames()]
            self.train_anchors = frame_anchors(sequence, self.train_kf, lambda f: not any(f in r for r in held),
                                               self.judge_config)
        self._batch_ids: List[List[int]] = []
        for name, child in model.named_children():
            child.requires_grad_(cfg.trains(name))
        self.measure_grad = cfg.trains('features') or cfg.trains('cost_volume')
        params = [p for p in model.parameters() if p.requires_grad]
        self.optimizer = torch.optim.AdamW(params, lr=cfg.lr, weight_decay=0.0)

    def held_frames(self) -> List[List[int]]:
        """The held-out frame ranges [first, last] (inclusive): one per block of consecutive held-out keyframes."""
        kfs = sorted(set(self.train_kf) | set(self.held_kf))
        held = set(self.held_kf)
        out: List[List[int]] = []
        for i, k in enumerate(kfs):
            if k in held and (i == 0 or kfs[i - 1] not in held):
                out.append([k, k])
            elif k in held:
                out[-1][1] = k
        if self.split is not None and out:        # the last frames: to the recording's end
            out[-1] = [self.split, len(self.seq) - 1]
        return out

    # ------------------------------------------------------------------ data
    def _sample(self, ids: Seq[int], rng: np.random.Generator) -> Dict[str, torch.Tensor]:
        return sample_from_sequence(self.seq, ids, self.cfg.layout(), rng, augment=None)

    def training_batch(self, rng: np.random.Generator) -> Dict[str, torch.Tensor]:
        out, self._batch_ids = [], []
        for _ in range(self.cfg.batch_size):
            ids = self.train_runs[int(rng.integers(0, len(self.train_runs)))]
            if rng.random() < 0.5:          # played backwards: another trajectory through the same place
                ids = ids[::-1]
            out.append(self._sample(ids, rng))
            self._batch_ids.append(list(ids))
        return _collate(out)

    # ------------------------------------------------------------------ losses
    def _photometric(self, batch, meas, res, automask: bool) -> Tuple[List[torch.Tensor], List[torch.Tensor]]:
        """Per unrolled step: the R-Net output's and the measurement's masked photometric errors."""
        cfg = self.cfg
        full, quarter = [], []
        K = batch['K']
        for m, r in zip(meas, res):
            srcs = batch['images'][:, m['sources']]
            depth = dpvops.depth_estimate(r['logp_full'].float(), self.depths_d, cfg.readout)
            err, mask = reprojection_error(m['image'], srcs, depth, K, m['T_src_ref'], automask=automask)
            full.append(masked_mean(err, mask))
            if cfg.aux > 0 and self.measure_grad and torch.is_grad_enabled():
                dq = dpvops.depth_estimate(m['logp_q'].float(), self.depths_d, cfg.readout)
                B, S = srcs.shape[:2]
                srcs_q = downsample_image(srcs.reshape(B * S, *srcs.shape[2:]))
                eq, mq = reprojection_error(downsample_image(m['image']), srcs_q.reshape(B, S, *srcs_q.shape[1:]),
                                            dq, m['K_vol'], m['T_src_ref'], automask=automask)
                quarter.append(masked_mean(eq, mq))
        return full, quarter

    def _evidence(self, batch, meas, res) -> Tuple[torch.Tensor, torch.Tensor]:
        """The photometric evidence (mean over the unrolled steps) of the R-Net output on the DPV grid and of the
        measurement."""
        full, quarter = [], []
        for m, r in zip(meas, res):
            e, ident = plane_errors(m['image'], batch['images'][:, m['sources']], batch['K'], m['T_src_ref'],
                                    self.depths_d)
            h, w = e.shape[-2:]
            full.append(photometric_evidence(r['logp_full'][:, :, ::4, ::4][..., :h, :w].float(), e, ident,
                                             self.cfg.sigma))
            quarter.append(photometric_evidence(m['logp_q'].float(), e, ident, self.cfg.sigma))
        return torch.stack(full).mean(), torch.stack(quarter).mean()

    def loss(self, batch) -> Tuple[torch.Tensor, Dict[str, float]]:
        """The loss of one batch (see the module docstring) and its terms."""
        cfg = self.cfg
        if cfg.supervised:
            loss, stats = run_unrolled(self.model, batch, self.depths_d, cfg.aux, measure_grad=self.measure_grad)
            stats = {'loss': stats['loss'], 'nll': stats['nll_full']}
        else:
            with torch.set_grad_enabled(self.measure_grad):
                meas = measure_steps(self.model, batch)
            res = filter_steps(self.model, meas, self.depths_d, 'knet')
            loss = torch.zeros(())
            stats = {}
            if cfg.photometric > 0:
                full, quarter = self._photometric(batch, meas, res, cfg.automask)
                ph = torch.stack(full).mean()
                loss = loss + cfg.photometric * ph
                stats['photometric'] = float(ph.detach())
                if quarter:
                    q = torch.stack(quarter).mean()
                    loss = loss + cfg.photometric * cfg.aux * q
                    stats['photometric_q'] = float(q.detach())
            if cfg.evidence > 0:
                ev, ev_q = self._evidence(batch, meas, res)
                loss = loss + cfg.evidence * (ev + cfg.aux * ev_q)
                stats['evidence'] = float(ev.detach())
                stats['evidence_q'] = float(ev_q.detach())
            if cfg.anchor_loss > 0 and self._batch_ids:
                terms = []
                for m, r in zip(meas, res):
                    depth = dpvops.depth_estimate(r['logp_full'].float(), self.depths_d, cfg.readout)
                    anchors = [self.train_anchors.get(ids[m['ref']]) for ids in self._batch_ids]
                    term = anchor_loss(depth, anchors, self.judge_config)
                    if term is not None:
                        terms.append(term)
                if terms:
                    al = torch.stack(terms).mean()
                    loss = loss + cfg.anchor_loss * al
                    stats['anchor'] = float(al.detach())
            if self.base_model is not None:
                with torch.no_grad():
                    bmeas = measure_steps(self.base_model, batch)
                    bres = filter_steps(self.base_model, bmeas, self.depths_d, 'knet')
                kl = torch.stack([distillation(r['logp_full'].float(), b['logp_full'].float(),
                                               self._tie_weight(b['logp_full'].float()))
                                  for r, b in zip(res, bres)]).mean()
                loss = loss + cfg.distill * kl
                stats['distill'] = float(kl.detach())
        if cfg.penalty > 0:
            pen = parameter_penalty(self.model.named_parameters(), self.base)
            loss = loss + cfg.penalty * pen
            stats['penalty'] = float(pen.detach())
        stats['loss'] = float(loss.detach())
        return loss, stats

    def _tie_weight(self, logp_base_bdhw: torch.Tensor) -> Optional[torch.Tensor]:
        """The distillation's weight per pixel: None (every pixel alike), or with ``distill_pixels='confident'``
        :func:`confidence_tie_weight` of the base network's published confidence at its own readout."""
        cfg = self.cfg
        if cfg.distill_pixels == 'all':
            return None
        with torch.no_grad():
            depth = dpvops.depth_estimate(logp_base_bdhw, self.depths_d, cfg.readout)
            conf = dpvops.published_confidence(logp_base_bdhw, self.depths_d, depth, P.default('confidence'),
                                               P.default('confidence_ratio'))
        return confidence_tie_weight(conf, cfg.distill_threshold)

    # ------------------------------------------------------------------ held-out score
    @torch.no_grad()
    def score(self, examples: int = 0) -> Tuple[Dict[str, Tuple[float, List[float]]], List[int], List[Dict]]:
        """The held-out scores of the model as it is now (see the module docstring): per kind ('photometric' or
        'nll', and 'anchors' when the judge is the anchors') the mean and the score of each held-out run; the anchors
        each run's score counted; and ``examples`` of its outputs (the last unrolled step of evenly spread held-out
        runs: image, depth and confidence at the node's readout)."""
        cfg = self.cfg
        was = self.model.training
        self.model.eval()
        rng = np.random.default_rng(0)
        num, den = 0.0, 0.0
        per_run: List[float] = []
        anchor_runs: List[float] = []
        anchor_counts: List[int] = []
        pick = set(np.linspace(0, len(self.held_runs) - 1, examples).round().astype(int).tolist()) if examples \
            else set()
        out = []
        readout = dpvops.resolve_readout(P.default('depth_readout'), learned=True)
        try:
            for i, ids in enumerate(self.held_runs):
                batch = self._sample(ids, rng)
                batch = _collate([batch])
                meas = measure_steps(self.model, batch)
                res = filter_steps(self.model, meas, self.depths_d, 'knet')
                run_num, run_den = 0.0, 0.0
                if self.held_anchors:
                    judged = AnchorScore(self.judge_config)
                    for m, r in zip(meas, res):
                        d = dpvops.depth_estimate(r['logp_full'].float(), self.depths_d, readout)
                        judged.add(d[0].numpy(), self.held_anchors.get(int(ids[m['ref']])))
                    anchor_runs.append(judged.value)
                    anchor_counts.append(judged.count)
                if cfg.supervised:
                    for m, r in zip(meas, res):
                        valid = dpvops.valid_depth_mask(m['gt'], self.model.d_min, self.model.d_max)
                        nll = dpvops.nll(r['logp_full'].float(), self.depths_d, m['gt'])
                        n = float(valid.sum())
                        run_num += float(nll) * n
                        run_den += n
                else:
                    for m, r in zip(meas, res):
                        depth = dpvops.depth_estimate(r['logp_full'].float(), self.depths_d, cfg.readout)
                        srcs = batch['images'][:, m['sources']]
                        err = score_error(m['image'], srcs, depth, batch['K'], m['T_src_ref'])
                        run_num += float(err.sum())
                        run_den += float(err.numel())
                num, den = num + run_num, den + run_den
                per_run.append(run_num / run_den if run_den > 0 else float('nan'))     # nan: nothing scored
                if i in pick:
                    logp = res[-1]['logp_full'].float()
                    d = dpvops.depth_estimate(logp, self.depths_d, readout)
                    c = dpvops.confidence(logp, self.depths_d, readout, depth_bhw=d)
                    out.append({'frame': int(ids[meas[-1]['ref']]),
                                'image': meas[-1]['image'][0].permute(1, 2, 0).numpy(),
                                'depth': d[0].numpy(), 'confidence': c[0].numpy()})
        finally:
            self.model.train(was)
        kind = 'nll' if cfg.supervised else 'photometric'
        scores = {kind: ((num / den if den > 0 else float('nan')), per_run)}
        if self.held_anchors:
            finite = [v for v in anchor_runs if math.isfinite(v)]
            scores['anchors'] = (float(np.mean(finite)) if finite else float('nan'), anchor_runs)
        return scores, anchor_counts, out

    def learning_rate(self, step: int, time_fraction: float) -> float:
        """Linear warm-up over ``warmup`` steps, then a cosine decay to ``min_lr_ratio`` of ``lr`` over the run, so its
        last steps only polish: the run's fraction done is ``step / max_steps`` when ``max_steps`` is set (the same
        rates every time: the weights are reproducible), else the training time's share of the time left to it."""
        cfg = self.cfg
        frac = min(1.0, step / cfg.max_steps if cfg.max_steps else max(0.0, time_fraction))
        warm = min(1.0, (step + 1) / max(1, cfg.warmup))
        return cfg.lr * warm * (cfg.min_lr_ratio + (1 - cfg.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * frac)))

    # ------------------------------------------------------------------ the run
    def run(self, deadline: float, progress: bool = True, examples: int = 3,
            on_step: Optional[Callable[[int, Dict], None]] = None) -> AdaptResult:
        """Score the base weights, adapt until ``max_steps`` or the ``deadline`` (a ``time.time()`` value) leaves
        no room for one more step and the final score, score the adapted weights. KeyboardInterrupt propagates."""
        from tqdm import tqdm
        cfg = self.cfg
        torch.manual_seed(cfg.seed)
        rng = np.random.default_rng(cfg.seed)
        seconds: Dict[str, float] = {}
        t0 = time.time()
        base, counts, base_examples = self.score(examples)
        seconds['base_score'] = time.time() - t0
        kind = 'nll' if cfg.supervised else cfg.judge
        self.log(f'held-out score of the base weights: {base[kind][0]:.5f} ({kind}; {len(self.held_runs)} runs, '
                 f'{seconds["base_score"]:.0f} s)')
        anchors = None
        if 'anchors' in base:
            judged = sum(math.isfinite(v) for v in base['anchors'][1])
            anchors = {'per_run': counts, 'runs_judged': judged, 'min_anchors': self.judge_config.min_anchors}
            need = runs_needed(cfg.significance)
            if kind == 'anchors' and judged < need:
                reason = (f'the held-out keyframes have too few metric anchors to judge the depth: {judged} of '
                          f'{len(self.held_runs)} held-out runs have {self.judge_config.min_anchors} or more (anchors '
                          f'per run: {", ".join(str(c) for c in counts)}), {need} are needed at significance '
                          f'{cfg.significance:g}. Anchors need the camera to move sideways past textured surfaces; '
                          'a camera turning in place or facing blank walls gives none. Record more of that motion, '
                          'or judge by photometry alone (--judge photometric), which cannot see depth where the '
                          'images have no texture')
                verdict = judge(base[kind][1], base[kind][1], cfg.significance, kind)
                verdict = dataclasses.replace(verdict, better=False, reason=reason)
                return AdaptResult(steps=0, base_score=float(base[kind][0]), adapted_score=float(base[kind][0]),
                                   score_kind=kind, stop_reason='judge', seconds=seconds, history=[],
                                   examples=[], verdict=verdict, anchors=anchors, refused=reason,
                                   keyframes=self._keyframe_stats())
        history: List[Dict] = []
        step, step_s, stop = 0, 0.0, 'max_steps'
        bar = tqdm(total=cfg.max_steps or None, disable=not progress, desc='adapt', unit='step', dynamic_ncols=True)
        t_train = time.time()
        reserve = seconds['base_score'] * 1.1 + 5.0          # the adapted weights' score, and a margin
        self.model.train()
        try:
            while not cfg.max_steps or step < cfg.max_steps:
                if time.time() + step_s * 1.2 + reserve > deadline:
                    stop = 'minutes'
                    break
                ts = time.time()
                lr = self.learning_rate(step, (ts - t_train) / max(1e-6, deadline - reserve - t_train))
                for g in self.optimizer.param_groups:
                    g['lr'] = lr
                batch = self.training_batch(rng)
                loss, stats = self.loss(batch)
                self.optimizer.zero_grad(set_to_none=True)
                loss.backward()
                gnorm = torch.nn.utils.clip_grad_norm_([p for p in self.model.parameters() if p.requires_grad],
                                                       cfg.clip)
                if torch.isfinite(gnorm):
                    self.optimizer.step()
                step += 1
                dt = time.time() - ts
                step_s = dt if step == 1 else 0.8 * step_s + 0.2 * dt
                stats.update(step=step, lr=lr, grad_norm=float(gnorm), seconds=dt)
                history.append(stats)
                bar.update(1)
                bar.set_postfix(loss=f"{stats['loss']:.4f}")
                if on_step is not None:
                    on_step(step, stats)
        finally:
            bar.close()
        seconds['train'] = time.time() - t_train
        t1 = time.time()
        adapted, _, adapted_examples = self.score(examples) if step else (base, counts, base_examples)
        seconds['adapted_score'] = time.time() - t1
        verdicts = {k: judge(base[k][1], adapted[k][1], cfg.significance, k) for k in base}
        verdict = verdicts[kind]
        beside = {k: {'base': float(base[k][0]), 'adapted': float(adapted[k][0]), 'verdict': v.to_json(),
                      'base_runs': list(base[k][1]), 'adapted_runs': list(adapted[k][1])}
                  for k, v in verdicts.items() if k != kind}
        if kind == 'anchors' and verdict.better:
            # the photometric score beside the judge: adapted weights it finds worse by its own test are not taken
            why = veto(base['photometric'][1], adapted['photometric'][1], cfg.significance, 'photometric')
            if why:
                verdict = dataclasses.replace(verdict, better=False, reason=why)
        self.log(f'held-out {kind} score after {step} steps: {adapted[kind][0]:.5f} (base {base[kind][0]:.5f}; '
                 f'{verdict.runs_better} of {verdict.runs} runs better, sign-flip p {verdict.p_value:.3f})'
                 + ''.join(f'; {k} {b["base"]:.5f} -> {b["adapted"]:.5f}' for k, b in beside.items()))
        ex = [{**b, 'depth_adapted': a['depth'], 'confidence_adapted': a['confidence']}
              for b, a in zip(base_examples, adapted_examples)]
        return AdaptResult(steps=step, base_score=float(base[kind][0]), adapted_score=float(adapted[kind][0]),
                           score_kind=kind, stop_reason=stop, seconds=seconds, history=history, examples=ex,
                           verdict=verdict, beside=beside, anchors=anchors, keyframes=self._keyframe_stats(),
                           runs={'base': list(base[kind][1]), 'adapted': list(adapted[kind][1])})

    def _keyframe_stats(self) -> Dict:
        return {'training': len(self.train_kf), 'held_out': len(self.held_kf), 'held_out_runs': len(self.held_runs),
                'split_frame': self.split, 'holdout_layout': self.holdout_layout,
                'held_out_frames': self.held_frames()}
