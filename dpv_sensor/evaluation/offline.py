"""Offline evaluation of the virtual depth camera (ROS-free).

Two ways in, one way out:

1. **Run the estimator** over a posed RGB-D sequence (a sequence folder, or an in-memory
   :class:`~dpv_sensor.data.sequence.Sequence`, e.g. from the synthetic renderer): frames are pushed in
   order into :class:`~dpv_sensor.stream.estimator.Estimator` with poses from the chosen *pose source*
   (``gt``: the sequence's poses; ``noisy``: the GT trajectory with odometry-like drift from
   :func:`dpv_sensor.data.trajectory.corrupt_trajectory`); with ``pose_refinement=window`` a
   :class:`dpv_sensor.stream.poses.WindowPoseRefiner` is plugged in. Every keyframe output is matched to its frame
   by stamp and kept as a :class:`KeyframeRecord` (prediction, confidence, K, poses, GT depth, image).
2. **Score recorded outputs**: a rosbag2 of the node's ``depth/image`` (+ ``confidence/image``,
   ``depth/camera_info``) read with :mod:`dpv_sensor.data.rosbag_io`, or a folder written by
   ``rosbag_io.export_depth_bag``; each depth image is matched to the GT sequence frame with the same stamp.

Scoring (:func:`score_records`, :mod:`dpv_sensor.evaluation.metrics`): depth metrics on every record, metric and
per-frame median-scaled; coverage; confidence quality (sparsification, AUSE, confident-half ratio);
temporal consistency between consecutive records (skipped across a filter reset), always computed with the
**GT poses** so that it measures the depth maps, not the pose source, and restricted to pixels visible in
both frames according to the GT depth. The summary's headline numbers are **frame means** (every keyframe
counts the same); the pooled, pixel-weighted numbers are reported next to them.

Depth range and resizing (documented for the ``evaluate`` tool too):

- GT pixels outside ``[min_depth, max_depth]`` are not scored and predictions are clipped to that range.
  By default the range is the estimator's depth planes ``[d_min, d_max]`` (the network checkpoint's, or the
  ``d_min`` / ``d_max`` parameters for the classical model), since no prediction can lie outside it.
- ``width`` / ``height`` resize the *input* sequence before anything else (images with area averaging, GT
  depth with centre-aligned nearest neighbour, K scaled with the project convention). The estimator then
  resizes to its ``processing_width x processing_height``; with ``output_resolution=input`` (default) the
  output and the scoring are at the (resized) input size, with ``processing`` at the processing size, the GT
  being resized to it with centre-aligned nearest neighbour (no depth interpolated across edges).

Outputs of :func:`write_report`: ``frames.csv`` (one row per keyframe), ``summary.json`` (metrics,
temporal consistency, AUSE, confident-half ratio, configuration, estimator status, timing),
``montage.png`` (image | GT | prediction | confidence | abs-rel error for a few frames, shared colour
scale) and ``sparsification.png``. :func:`compare` runs several configurations and writes
``compare.md`` / ``compare.json`` (and an overlaid sparsification plot).
"""
from __future__ import annotations

import csv
import dataclasses
import itertools
import json
import logging
import math
import pathlib
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Dict, Iterable, List, Optional, Sequence as SequenceT, Tuple, Union

import cv2
import numpy as np

from dpv_sensor.evaluation import metrics as M
from dpv_sensor.core.geometry import relative_pose_error_np
from dpv_sensor.common import to_jsonable
from dpv_sensor.evaluation.consumer_odometry import (  # noqa: F401
    CONSUMER_ODOMETRY_DEPTH_MAX, add_consumer_odometry, consumer_odometry, consumer_odometry_text)
from dpv_sensor import params as P

if TYPE_CHECKING:
    from dpv_sensor.stream.estimator_config import EstimatorStatus

LOG = logging.getLogger('dpv_sensor.evaluation.offline')

__all__ = ['POSE_SOURCES', 'EVAL_KEYS', 'EvalOptions', 'KeyframeRecord', 'parse_value', 'parse_overrides',
           'build_config', 'load_sequence', 'load_source', 'prepare_sequence', 'run_sequence', 'score_records',
           'summarize', 'write_report', 'evaluate_sequence', 'compare', 'variants_from_specs',
           'markdown_table', 'records_from_bag', 'records_from_export', 'evaluate_records', 'to_jsonable',
           'relative_pose_error', 'consumer_odometry', 'evaluate_offline']

POSE_SOURCES = ('gt', 'noisy')
# compare() keeps the decoded frames in memory for all variants when they take less than this (RGB + depth).
MATERIALIZE_BYTES = 256 * 2 ** 20
# Keys a configuration may carry that are evaluation settings, not estimator parameters.
EVAL_KEYS = ('pose_source',)


# ----------------------------------------------------------------------------------------------
# Options and records
# ----------------------------------------------------------------------------------------------

@dataclass
class EvalOptions:
    """How a sequence is evaluated (not estimator parameters).

    min_depth / max_depth: GT range scored (None: the estimator's d_min / d_max). width / height: resize
    the input sequence first (both or neither). start / max_frames: the frames used. pose_source: 'gt' or
    'noisy' (``pose_noise`` = (relative translation noise per step, rotation noise deg per step), seeded
    by ``seed``). montage_frames: rows of the montage. occlusion_tol: relative GT-depth agreement that
    counts a pixel as visible in both frames for temporal consistency. progress: tqdm bars.
    consumer_odometry: add :func:`consumer_odometry` (Open3D RGB-D odometry on predicted vs GT depth) to the
    summary.
    """
    min_depth: Optional[float] = None
    max_depth: Optional[float] = None
    width: Optional[int] = None
    height: Optional[int] = None
    start: int = 0
    max_frames: Optional[int] = None
    pose_source: str = 'gt'
    pose_noise: Tuple[float, float] = (0.03, 0.5)
    seed: int = 0
    montage_frames: int = 4
    occlusion_tol: float = 0.05
    progress: bool = True
    consumer_odometry: bool = True

    def validate(self) -> 'EvalOptions':
        if self.pose_source not in POSE_SOURCES:
            raise ValueError(f'pose_source {self.pose_source!r} is not one of {list(POSE_SOURCES)}')
        if (self.width is None) != (self.height is None):
            raise ValueError('give both width and height to resize, or neither')
        if self.min_depth is not None and self.max_depth is not None and self.min_depth >= self.max_depth:
            raise ValueError(f'min_depth {self.min_depth} must be below max_depth {self.max_depth}')
        return self


@dataclass
class KeyframeRecord:
    """One scored output.

    depth_hw: float32 metres, NaN = no estimate; confidence_hw: [0, 1] or None; K_33: intrinsics of the
    depth map's size; T_world_cam_44: the pose the estimator used (None when unknown, e.g. from a bag);
    gt_depth_hw: GT at the depth map's size (0 = invalid); gt_T_world_cam_44: GT pose; image_hw3: colour
    at the depth map's size (for montages) or None; reset_reason: set when the filter restarted here.
    """
    index: int
    stamp: float
    depth_hw: np.ndarray
    confidence_hw: Optional[np.ndarray]
    K_33: np.ndarray
    gt_depth_hw: np.ndarray
    gt_T_world_cam_44: Optional[np.ndarray]
    T_world_cam_44: Optional[np.ndarray] = None
    image_hw3: Optional[np.ndarray] = None
    reset_reason: Optional[str] = None
    time_ms: float = float('nan')


# ----------------------------------------------------------------------------------------------
# Configuration
# ----------------------------------------------------------------------------------------------

parse_value = P.parse_value


def _known_keys() -> Dict[str, Any]:
    """Every key a configuration may set, with a value of its type: every setting of the table (node
    parameters and the estimator's library settings) and the evaluation keys."""
    keys: Dict[str, Any] = {name: spec.default for name, spec in P.SPEC_BY_NAME.items()}
    keys['pose_source'] = 'gt'
    return keys


def parse_overrides(items: Iterable[str]) -> Dict[str, Any]:
    """``['filter_mode=global', 'damping=0.5']`` -> typed dict; unknown keys raise ValueError."""
    return P.parse_assignments(items, _known_keys())


def build_config(overrides: Optional[Dict[str, Any]] = None):
    """(EstimatorConfig, validated parameter dict) from the node defaults plus ``overrides``.

    Evaluation keys (``pose_source``) are ignored here. Raises ``params.ParameterError`` / ValueError.
    """
    from dpv_sensor.stream.estimator import EstimatorConfig
    values = P.defaults(P.SPECS + P.LIBRARY_SPECS)
    for k, v in (overrides or {}).items():
        if k not in EVAL_KEYS:
            values[k] = v
    values = P.validate(values, P.SPECS + P.LIBRARY_SPECS)
    return EstimatorConfig.from_params(values), values


# ----------------------------------------------------------------------------------------------
# Sequences
# ----------------------------------------------------------------------------------------------

def load_sequence(seq) -> Any:
    """A :class:`~dpv_sensor.data.sequence.Sequence` from a folder path; other objects pass through."""
    if isinstance(seq, (str, pathlib.Path)):
        from dpv_sensor.data.sequence import Sequence
        return Sequence(seq)
    return seq


def load_source(text: str, width: Optional[int], height: Optional[int]):
    """A sequence folder path, or ``synthetic:SEED[:FRAMES]`` rendered in memory."""
    if text.startswith('synthetic:'):
        from dpv_sensor.data.synthetic import render_sequence
        parts = text.split(':')
        seed = int(parts[1])
        frames = int(parts[2]) if len(parts) > 2 else 60
        return render_sequence(seed, frames, width=width or 320, height=height or 240)
    path = pathlib.Path(text)
    if not path.is_dir():
        raise ValueError(f'{path} is not a sequence folder')
    return path


def prepare_sequence(seq, options: EvalOptions):
    """Load, cut to ``start`` / ``max_frames`` and resize as the options say."""
    seq = load_sequence(seq)
    n = len(seq)
    stop = n if options.max_frames is None else min(n, options.start + int(options.max_frames))
    if options.start or stop < n:
        if not hasattr(seq, 'subset'):
            raise ValueError('start / max_frames need a Sequence (with subset())')
        seq = seq.subset(range(options.start, stop))
    if options.width is not None:
        seq = seq.resized(int(options.width), int(options.height))
    return seq


def _resize_nearest(a: np.ndarray, hw: Tuple[int, int]) -> np.ndarray:
    if a.shape[:2] == tuple(hw):
        return a
    return cv2.resize(a, (int(hw[1]), int(hw[0])), interpolation=cv2.INTER_NEAREST_EXACT)


def _resize_image(img: np.ndarray, hw: Tuple[int, int]) -> np.ndarray:
    if img.shape[:2] == tuple(hw):
        return img
    shrink = hw[0] <= img.shape[0] and hw[1] <= img.shape[1]
    return cv2.resize(img, (int(hw[1]), int(hw[0])), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)


def input_poses(seq, options: EvalOptions) -> List[np.ndarray]:
    """The poses the estimator is fed: GT, or (``pose_source='noisy'``) an odometry-like corruption of them."""
    gt = [np.asarray(seq.pose(i), np.float64) for i in range(len(seq))]
    if options.pose_source == 'gt':
        return gt
    from dpv_sensor.data.trajectory import corrupt_trajectory
    return corrupt_trajectory(gt, trans_noise_rel=float(options.pose_noise[0]),
                              rot_noise_deg=float(options.pose_noise[1]), seed=options.seed)


# ----------------------------------------------------------------------------------------------
# Running the estimator
# ----------------------------------------------------------------------------------------------

def run_sequence(seq, config, options: Optional[EvalOptions] = None, *, model=None, pose_refiner=None,
                 keep_images: bool = True) -> Tuple[List[KeyframeRecord], EstimatorStatus]:
    """Push the (prepared) sequence through an estimator; return (keyframe records, estimator status).

    config: an ``EstimatorConfig``; the pose source comes from it (``pipeline.PoseSource``): with
    ``pose_refinement='window'`` and no ``pose_refiner`` given, a WindowPoseRefiner with the config's sigmas,
    with ``odometry='none'`` visual odometry instead of the sequence's poses. ``model``: a DPVNet to use
    instead of loading weights (see ``Estimator``).
    """
    from dpv_sensor.stream.frame import Frame
    from dpv_sensor.stream.pipeline import Pipeline
    options = (options or EvalOptions()).validate()
    seq = prepare_sequence(seq, options)
    pipe = Pipeline(config, model=model, pose_refiner=pose_refiner)
    poses_in = input_poses(seq, options)
    K = np.asarray(seq.K, np.float64)
    index_of: Dict[float, int] = {}
    records: List[KeyframeRecord] = []
    iterator: Iterable[int] = range(len(seq))
    if options.progress:
        from tqdm import tqdm
        iterator = tqdm(iterator, desc='estimating', unit='frame', leave=False)
    for i in iterator:
        stamp = float(seq.stamp(i))
        index_of[stamp] = i
        out = pipe.push(Frame(stamp=stamp, image=seq.image(i), K_33=K, T_world_cam_44=poses_in[i],
                              frame_id='camera')).output
        if out is None or not out.is_keyframe:
            continue
        j = index_of[out.stamp]
        hw = out.depth_hw.shape
        gt = _resize_nearest(np.asarray(seq.depth(j), np.float32), hw)
        image = _resize_image(seq.image(j), hw) if keep_images else None
        records.append(KeyframeRecord(
            index=j, stamp=out.stamp, depth_hw=out.depth_hw, confidence_hw=out.confidence_hw,
            K_33=np.asarray(out.K_33, np.float64), gt_depth_hw=gt, gt_T_world_cam_44=np.asarray(seq.pose(j)),
            T_world_cam_44=None if out.T_world_cam_44 is None else np.asarray(out.T_world_cam_44),
            image_hw3=image, reset_reason=out.reset_reason,
            time_ms=float(out.timings_ms.get('total', float('nan')))))
    return records, pipe.status


def status_json(status: EstimatorStatus) -> Dict[str, Any]:
    """The estimator status as ``summary.json`` holds it: its fields (``EstimatorStatus.as_dict``) and the ends of
    its depth range (d_min, d_max)."""
    out = status.as_dict()
    out['depth_range'] = list(status.depth_range)
    out['d_min'], out['d_max'] = (float(d) for d in status.depth_range)
    return out


# ----------------------------------------------------------------------------------------------
# Scoring
# ----------------------------------------------------------------------------------------------

def _pose_error(T_est: Optional[np.ndarray], T_gt: Optional[np.ndarray]) -> Tuple[float, float]:
    if T_est is None or T_gt is None:
        return float('nan'), float('nan')
    return relative_pose_error_np(T_gt, T_est)


def score_records(records: SequenceT[KeyframeRecord], *, min_depth: Optional[float] = None,
                  max_depth: Optional[float] = None, occlusion_tol: float = 0.05,
                  progress: bool = False) -> M.MetricAccumulator:
    """Metrics of every record plus temporal consistency of consecutive records.

    Per-frame rows carry: index, stamp, time_ms, the metrics (``ms_`` = median-scaled), coverage,
    ause / confident_half_ratio / mean_confidence, ``temporal`` (consistency with the previous record, NaN
    for the first record and after a reset), and the pose error of the pose used (m, deg) when known.
    """
    acc = M.MetricAccumulator(min_depth=min_depth, max_depth=max_depth)
    iterator: Iterable = enumerate(records)
    if progress:
        from tqdm import tqdm
        iterator = tqdm(iterator, total=len(records), desc='scoring', unit='frame', leave=False)
    prev: Optional[KeyframeRecord] = None
    for _, r in iterator:
        te, re = _pose_error(r.T_world_cam_44, r.gt_T_world_cam_44)
        row = acc.add(r.depth_hw, r.gt_depth_hw, r.confidence_hw, K=r.K_33, index=r.index, stamp=r.stamp,
                      time_ms=r.time_ms, pose_err_m=te, pose_err_deg=re, reset=bool(r.reset_reason))
        row['temporal'] = float('nan')
        row['temporal_pixels'] = 0
        if prev is not None and not r.reset_reason:
            Ta = prev.gt_T_world_cam_44 if prev.gt_T_world_cam_44 is not None else prev.T_world_cam_44
            Tb = r.gt_T_world_cam_44 if r.gt_T_world_cam_44 is not None else r.T_world_cam_44
            if Ta is not None and Tb is not None:
                val, n = M.temporal_consistency(prev.depth_hw, r.depth_hw, prev.K_33, r.K_33, Ta, Tb,
                                                gt_a=prev.gt_depth_hw, gt_b=r.gt_depth_hw,
                                                occlusion_tol=occlusion_tol)
                acc.add_temporal(val, n)
                row['temporal'] = val
                row['temporal_pixels'] = n
        prev = r
    return acc


def pose_rpe(records: SequenceT[KeyframeRecord]) -> Optional[Dict[str, float]]:
    """Relative pose error of the poses the estimator used (odometry, or refined), between consecutive records
    (keyframe outputs) against the GT poses: median and mean translation (m) and rotation (deg) over the pairs, or
    None without GT poses. Unlike the absolute pose error it does not grow with the odometry's drift."""
    et, er = [], []
    for a, b in zip(records[:-1], records[1:]):
        if any(T is None for T in (a.T_world_cam_44, b.T_world_cam_44, a.gt_T_world_cam_44, b.gt_T_world_cam_44)):
            continue
        est = np.linalg.inv(a.T_world_cam_44) @ b.T_world_cam_44
        gt = np.linalg.inv(a.gt_T_world_cam_44) @ b.gt_T_world_cam_44
        t, r = relative_pose_error(est, gt)
        et.append(t)
        er.append(r)
    if not et:
        return None
    return {'pairs': len(et), 'median_m': float(np.median(et)), 'mean_m': float(np.mean(et)),
            'median_deg': float(np.median(er)), 'mean_deg': float(np.mean(er))}


def relative_pose_error(T_est_44: np.ndarray, T_gt_44: np.ndarray) -> Tuple[float, float]:
    """(translation m, rotation deg) of ``inv(T_gt) @ T_est``: how far an estimated relative motion is from
    the true one."""
    return _pose_error(np.asarray(T_est_44, np.float64), np.asarray(T_gt_44, np.float64))


def summarize(acc: M.MetricAccumulator, records: SequenceT[KeyframeRecord], *,
              configuration: Optional[Dict[str, Any]] = None, status: Optional[EstimatorStatus] = None,
              source: Optional[str] = None) -> Dict[str, Any]:
    """The JSON summary: ``MetricAccumulator.summary()`` plus timing, pose error, configuration, status."""
    s = acc.summary()
    times = np.array([r.time_ms for r in records], np.float64)
    times = times[np.isfinite(times)]
    s['num_keyframes'] = len(records)
    s['num_resets'] = sum(1 for r in records if r.reset_reason)
    s['time_ms_per_keyframe'] = {'mean': float(times.mean()) if times.size else float('nan'),
                                 'median': float(np.median(times)) if times.size else float('nan')}
    pe = np.array([row.get('pose_err_m', np.nan) for row in acc.rows], np.float64)
    pr = np.array([row.get('pose_err_deg', np.nan) for row in acc.rows], np.float64)
    if np.isfinite(pe).any():
        s['pose_error'] = {'mean_m': float(np.nanmean(pe)), 'mean_deg': float(np.nanmean(pr))}
    rpe = pose_rpe(records)
    if rpe is not None:
        s['pose_rpe'] = rpe
    if source is not None:
        s['source'] = source
    if configuration is not None:
        s['configuration'] = configuration
    if status is not None:
        s['estimator_status'] = status_json(status)
    return s


# ----------------------------------------------------------------------------------------------
# Reports
# ----------------------------------------------------------------------------------------------

_CSV_FIRST = ['index', 'stamp', 'time_ms', 'num_pixels', 'coverage'] + list(M.ERROR_METRICS) + \
    ['ms_' + k for k in M.ERROR_METRICS] + ['scale', 'ause', 'confident_half_ratio', 'mean_confidence',
                                            'temporal', 'temporal_pixels', 'pose_err_m', 'pose_err_deg', 'reset']


def write_frames_csv(rows: SequenceT[Dict], path) -> pathlib.Path:
    """One CSV row per scored frame (known columns first, then any extra keys)."""
    path = pathlib.Path(path)
    keys = [k for k in _CSV_FIRST if any(k in r for r in rows)]
    for r in rows:
        keys += [k for k in r if k not in keys]
    with open(path, 'w', newline='') as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        for r in rows:
            w.writerow({k: ('' if (isinstance(r.get(k), float) and not math.isfinite(r[k])) else r.get(k, ''))
                        for k in keys})
    return path


def _montage_rows(records: SequenceT[KeyframeRecord], n: int) -> List[Dict]:
    if not records or n <= 0:
        return []
    pick = np.unique(np.linspace(0, len(records) - 1, min(n, len(records))).round().astype(int))
    rows = []
    for k in pick:
        r = records[k]
        rows.append({'image': r.image_hw3, 'gt': r.gt_depth_hw, 'pred': r.depth_hw, 'confidence': r.confidence_hw,
                     'label': f'frame {r.index}'})
    return rows


def write_report(out_dir, acc: M.MetricAccumulator, records: SequenceT[KeyframeRecord], summary: Dict[str, Any],
                 *, montage_frames: int = 4, title: Optional[str] = None) -> Dict[str, str]:
    """Write frames.csv, summary.json, montage.png, sparsification.png and reliability.png; return {name: path}."""
    from dpv_sensor.evaluation import plots
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = {'frames_csv': str(write_frames_csv(acc.rows, out / 'frames.csv'))}
    rows = _montage_rows(records, montage_frames)
    if rows:
        files['montage'] = str(plots.montage(rows, out / 'montage.png', title=title))
    curves = acc.mean_curves()
    if curves is not None:
        files['sparsification'] = str(plots.sparsification_plot({title or 'prediction': curves},
                                                                out / 'sparsification.png', title=title))
        summary.setdefault('confidence', {})['mean_curves'] = {k: np.asarray(v).tolist() for k, v in curves.items()}
    if summary.get('calibration'):
        files['reliability'] = str(plots.reliability_plot({title or 'prediction': summary['calibration']},
                                                          out / 'reliability.png', title=title))
    summary['files'] = dict(files, summary=str(out / 'summary.json'))
    with open(out / 'summary.json', 'w') as f:
        json.dump(to_jsonable(summary), f, indent=1)
    files['summary'] = str(out / 'summary.json')
    return files


def depth_limits(options: EvalOptions, status: EstimatorStatus) -> Tuple[Optional[float], Optional[float]]:
    """(min, max) GT depth that is scored: the options' limits, else the estimator's depth range."""
    lo = options.min_depth if options.min_depth is not None else float(status.depth_range[0])
    hi = options.max_depth if options.max_depth is not None else float(status.depth_range[1])
    return lo, hi


def evaluate_sequence(seq, overrides: Optional[Dict[str, Any]] = None, out_dir=None,
                      options: Optional[EvalOptions] = None, *, model=None, name: Optional[str] = None,
                      return_records: bool = False):
    """Run the estimator over ``seq`` with the node defaults plus ``overrides``, score, and (with
    ``out_dir``) write the report. ``overrides['pose_source']`` overrides ``options.pose_source``.

    Returns the summary dict (and the records with ``return_records=True``).
    """
    options = dataclasses.replace(options or EvalOptions())
    overrides = dict(overrides or {})
    if 'pose_source' in overrides:
        options.pose_source = overrides['pose_source']
    options.validate()
    config, values = build_config(overrides)
    t0 = time.perf_counter()
    records, status = run_sequence(seq, config, options, model=model)
    wall = time.perf_counter() - t0
    lo, hi = depth_limits(options, status)
    acc = score_records(records, min_depth=lo, max_depth=hi, occlusion_tol=options.occlusion_tol,
                        progress=options.progress)
    seq_name = str(seq) if isinstance(seq, (str, pathlib.Path)) else getattr(seq, 'name', 'in-memory')
    configuration = {'overrides': overrides, 'parameters': values,
                     'options': dataclasses.asdict(options), 'depth_limits': [lo, hi]}
    summary = summarize(acc, records, configuration=configuration, status=status, source=seq_name)
    summary['wall_time_s'] = wall
    add_consumer_odometry(summary, records, options)
    if out_dir is not None:
        write_report(out_dir, acc, records, summary, montage_frames=options.montage_frames, title=name)
    return (summary, records) if return_records else summary


# ----------------------------------------------------------------------------------------------
# Comparing configurations
# ----------------------------------------------------------------------------------------------

def variants_from_specs(specs: Iterable[str]) -> List[Dict[str, Any]]:
    """``['filter_mode=none,global', 'measurement=classical']`` -> the cartesian product as typed dicts."""
    known = _known_keys()
    axes = []
    for spec in specs:
        if '=' not in spec:
            raise ValueError(f'expected key=v1,v2,..., got {spec!r}')
        key, values = spec.split('=', 1)
        key = key.strip()
        if key not in known:
            raise ValueError(f'unknown configuration key {key!r}; known: {", ".join(sorted(known))}')
        vals = [v.strip() for v in values.split(',') if v.strip()]
        if isinstance(known[key], list):
            raise ValueError(f'{key} is a list parameter and cannot be compared with --compare')
        axes.append([(key, parse_value(v, known[key])) for v in vals])
    return [dict(combo) for combo in itertools.product(*axes)] if axes else [{}]


def _variant_name(variant: Dict[str, Any]) -> str:
    return ' '.join(f'{k}={v}' for k, v in variant.items()) or 'default'


_TABLE_COLUMNS = [
    ('abs_rel', ('metric', 'frame_mean', 'abs_rel'), '{:.4f}'),
    ('sq_rel', ('metric', 'frame_mean', 'sq_rel'), '{:.4f}'),
    ('rmse', ('metric', 'frame_mean', 'rmse'), '{:.3f}'),
    ('rmse_log', ('metric', 'frame_mean', 'rmse_log'), '{:.3f}'),
    ('d1', ('metric', 'frame_mean', 'delta1'), '{:.3f}'),
    ('d2', ('metric', 'frame_mean', 'delta2'), '{:.3f}'),
    ('d3', ('metric', 'frame_mean', 'delta3'), '{:.3f}'),
    ('si_log', ('metric', 'frame_mean', 'si_log'), '{:.3f}'),
    ('ms abs_rel', ('median_scaled', 'frame_mean', 'abs_rel'), '{:.4f}'),
    ('ms d1', ('median_scaled', 'frame_mean', 'delta1'), '{:.3f}'),
    ('const abs_rel', ('constant', 'frame_mean', 'abs_rel'), '{:.4f}'),
    ('const d1', ('constant', 'frame_mean', 'delta1'), '{:.3f}'),
    ('coverage', ('coverage', 'frame_mean'), '{:.3f}'),
    ('edge abs_rel', ('edges', 'edge_abs_rel_frame_mean'), '{:.4f}'),
    ('non-edge abs_rel', ('edges', 'nonedge_abs_rel_frame_mean'), '{:.4f}'),
    ('normal°', ('edges', 'normal_err_deg_frame_mean'), '{:.1f}'),
    ('temporal', ('temporal_consistency', 'pair_mean'), '{:.4f}'),
    ('AUSE', ('confidence', 'ause_frame_mean'), '{:.4f}'),
    ('conf½/all', ('confidence', 'confident_half_ratio_frame_mean'), '{:.3f}'),
    ('conf½ pooled', ('confidence', 'confident_half_ratio_pooled'), '{:.3f}'),
    ('ECE', ('calibration', 'ece'), '{:.3f}'),
    ('mean conf', ('calibration', 'mean_confidence'), '{:.3f}'),
    ('kept@0.9', ('calibration', 'kept', '0.9', 'share'), '{:.3f}'),
    ('d1@0.9', ('calibration', 'kept', '0.9', 'delta1'), '{:.3f}'),
    ('odo t×', ('consumer_odometry', 'ratio_trans'), '{:.2f}'),
    ('odo r×', ('consumer_odometry', 'ratio_rot'), '{:.2f}'),
    ('ms/kf', ('time_ms_per_keyframe', 'mean'), '{:.0f}'),
    ('kf', ('num_keyframes',), '{:d}'),
]


def _get(d, path):
    for p in path:
        if not isinstance(d, dict) or p not in d:
            return None
        d = d[p]
    return d


def table_row(name: str, summary: Dict[str, Any]) -> Dict[str, Any]:
    """The numbers of one configuration as a flat dict (column name -> value, None when undefined)."""
    row: Dict[str, Any] = {'name': name}
    st = summary.get('estimator_status') or {}
    row['measurement'] = st.get('measurement')
    row['filter'] = st.get('filter_mode')
    for col, path, _fmt in _TABLE_COLUMNS:
        v = _get(summary, path)
        row[col] = None if v is None or (isinstance(v, float) and not math.isfinite(v)) else v
    return row


def markdown_table(rows: SequenceT[Dict[str, Any]]) -> str:
    """A markdown table of :func:`table_row` dicts (frame means; ``ms`` = median-scaled)."""
    cols = ['name', 'measurement', 'filter'] + [c for c, _p, _f in _TABLE_COLUMNS]
    fmts = {c: f for c, _p, f in _TABLE_COLUMNS}
    lines = ['| ' + ' | '.join(cols) + ' |', '|' + '|'.join('---' for _ in cols) + '|']
    for r in rows:
        cells = []
        for c in cols:
            v = r.get(c)
            if v is None:
                cells.append('-')
            elif c in fmts:
                try:
                    cells.append(fmts[c].format(v))
                except (ValueError, TypeError):
                    cells.append(str(v))
            else:
                cells.append(str(v))
        lines.append('| ' + ' | '.join(cells) + ' |')
    return '\n'.join(lines)


def compare(seq, base_overrides: Optional[Dict[str, Any]], variants: SequenceT[Dict[str, Any]], out_dir=None,
            options: Optional[EvalOptions] = None, *, model=None) -> Dict[str, Any]:
    """Evaluate every variant (``base_overrides`` updated with the variant) on the same frames.

    With ``out_dir``: one report per variant in ``out_dir/<nn>_<name>/``, plus ``compare.md``,
    ``compare.json`` and ``compare_sparsification.png``. Returns ``{'rows', 'markdown', 'summaries'}``.
    """
    from dpv_sensor.evaluation import plots
    options = options or EvalOptions()
    seq = prepare_sequence(seq, options)
    if hasattr(seq, 'materialize') and len(variants) > 1 and len(seq):
        w, h = seq.size
        if len(seq) * w * h * 7 < MATERIALIZE_BYTES:
            seq = seq.materialize()      # decode/resize the frames once for all variants
    inner = dataclasses.replace(options, start=0, max_frames=None, width=None, height=None)
    rows, summaries, curves = [], {}, {}
    out = pathlib.Path(out_dir) if out_dir is not None else None
    for k, variant in enumerate(variants):
        name = _variant_name(variant)
        ov = dict(base_overrides or {})
        ov.update(variant)
        sub = None
        if out is not None:
            safe = ''.join(ch if ch.isalnum() or ch in '-_.' else '_' for ch in name)
            sub = out / f'{k:02d}_{safe}'
        LOG.info('evaluating %s', name)
        summary = evaluate_sequence(seq, ov, sub, inner, model=model, name=name)
        summaries[name] = summary
        rows.append(table_row(name, summary))
        mc = _get(summary, ('confidence', 'mean_curves'))
        if mc is not None:
            curves[name] = {kk: np.asarray(v, np.float64) for kk, v in mc.items()}
    md = markdown_table(rows)
    result = {'rows': rows, 'markdown': md, 'summaries': summaries}
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / 'compare.md').write_text(md + '\n\nFrame means over keyframes; ms = per-frame median-scaled; '
                                        'temporal = mean abs relative disagreement of consecutive keyframes; '
                                        'conf½/all = abs_rel of the most confident half / abs_rel of all '
                                        '(per frame, mean over frames); conf½ pooled = the same over the pixels of '
                                        "all frames together; const = every pixel at the frame's median GT depth "
                                        '(an oracle constant) on the same keyframes and pixels.\n')
        with open(out / 'compare.json', 'w') as f:
            json.dump(to_jsonable({'rows': rows, 'base_overrides': base_overrides or {},
                                   'variants': list(variants), 'options': dataclasses.asdict(options)}), f, indent=1)
        if curves:
            plots.sparsification_plot(curves, out / 'compare_sparsification.png')
    return result


# ----------------------------------------------------------------------------------------------
# Recorded outputs (bags and exported folders)
# ----------------------------------------------------------------------------------------------

def _match(stamp: float, gt_stamps: np.ndarray, tolerance: float) -> Optional[int]:
    j = int(np.argmin(np.abs(gt_stamps - stamp)))
    return j if abs(gt_stamps[j] - stamp) <= tolerance else None


def _records_from_arrays(items, gt, *, tolerance: float, stamp_offset: float,
                         keep_images: bool = True) -> Tuple[List[KeyframeRecord], Dict[str, Any]]:
    """items: iterable of (stamp s, depth_hw, confidence_hw | None, K_33 | None)."""
    gt = load_sequence(gt)
    gt_stamps = np.array([gt.stamp(i) for i in range(len(gt))], np.float64)
    records, unmatched = [], 0
    K_gt = np.asarray(gt.K, np.float64)
    for stamp, depth, conf, K in items:
        j = _match(stamp - stamp_offset, gt_stamps, tolerance)
        if j is None:
            unmatched += 1
            continue
        depth = np.asarray(depth, np.float32)
        hw = depth.shape
        if K is None:
            from dpv_sensor.data.sequence import scale_intrinsics_np
            h0, w0 = np.asarray(gt.depth(j)).shape
            K = scale_intrinsics_np(K_gt, hw[1] / w0, hw[0] / h0)
        records.append(KeyframeRecord(
            index=j, stamp=float(stamp), depth_hw=depth, confidence_hw=conf, K_33=np.asarray(K, np.float64),
            gt_depth_hw=_resize_nearest(np.asarray(gt.depth(j), np.float32), hw),
            gt_T_world_cam_44=np.asarray(gt.pose(j)),
            image_hw3=_resize_image(gt.image(j), hw) if keep_images else None))
    return records, {'matched': len(records), 'unmatched': unmatched, 'stamp_offset_s': stamp_offset}


def first_image_stamp(bag, topic: str) -> float:
    """Header stamp (s) of the first message on `topic` of a rosbag2."""
    from dpv_sensor.ros import msgs as MS
    from dpv_sensor.data import rosbag_io as R
    messages = R.read_messages(bag, [topic])
    try:
        first = next(messages)[3]
    except StopIteration:
        raise R.BagError(f'{bag}: no message on {topic}') from None
    finally:
        messages.close()            # closes the bag reader
    return MS.stamp_to_ns(first.header.stamp) / R.NS


def gt_stamp_offset(first_stamp_s: float, gt_seq, tolerance: float = 1e-3) -> float:
    """The offset (s) to subtract from bag stamps to get GT stamps, from the bag's first camera image: 0 when that
    stamp is one of the GT frames' own stamps (stamps.txt in the bag's clock), else the bag's first image is GT
    frame 0 (a folder without stamps.txt counts from 0 at 30 Hz; a bag written from it may start at any epoch)."""
    stamps = np.array([float(gt_seq.stamp(i)) for i in range(len(gt_seq))])
    if stamps.size and float(np.min(np.abs(stamps - first_stamp_s))) <= tolerance:
        return 0.0
    return first_stamp_s - float(gt_seq.stamp(0))


def records_from_bag(bag, gt, *, depth_topic: Optional[str] = None, confidence_topic: Optional[str] = None,
                     info_topic: Optional[str] = None, image_topic: Optional[str] = None,
                     stamp_offset: Union[float, str] = 'auto',
                     tolerance: float = 1e-3) -> Tuple[List[KeyframeRecord], Dict[str, Any]]:
    """Depth outputs recorded in a bag, matched by header stamp to the frames of the GT sequence ``gt``.

    Topics default to ``/depth/image``, ``/confidence/image``, ``/depth/camera_info`` (or the only topic of
    that type ending the same way, for a namespaced node). ``stamp_offset`` (s) is subtracted from the bag
    stamps before matching; ``'auto'``: when the bag also holds the camera images, the first image stamp is
    taken to be GT frame 0 (a bag written by ``bag`` / ``write_sequence_bag`` from the sequence), else 0. The camera
    image topic is ``image_topic``, or the only sensor_msgs/Image topic besides the node's outputs
    (``rosbag_io.detect_topic``; several: BagError listing them).
    A depth image matches a GT frame within ``tolerance`` seconds; unmatched ones are counted and skipped.
    Returns (records, info).
    """
    from dpv_sensor.data import rosbag_io as R
    topics = R.bag_topics(bag)
    d_topic = R.find_topic(topics, depth_topic or R.DEPTH_TOPIC, 'depth/image', R.IMAGE)
    if d_topic is None:
        raise R.BagError(f'{bag}: no depth topic (topics: {sorted(topics)})')
    c_topic = R.find_topic(topics, confidence_topic or R.CONFIDENCE_TOPIC, 'confidence/image', R.IMAGE)
    i_topic = R.find_topic(topics, info_topic or R.DEPTH_INFO_TOPIC, 'depth/camera_info', R.CAMERA_INFO)
    depth = R.read_depth_images(bag, d_topic)
    conf = {s.stamp_ns: s.data for s in R.read_depth_images(bag, c_topic)} if c_topic else {}
    infos = {s.stamp_ns: s.data for s in R.read_camera_infos(bag, i_topic)} if i_topic else {}
    if stamp_offset == 'auto':
        gt_seq = load_sequence(gt)
        img_topic, img_how = R.detect_topic(topics, 'camera image', R.IMAGE, wanted=image_topic,
                                            option='--image-topic, or --stamp-offset', exclude=(d_topic, c_topic),
                                            required=False)
        offset = 0.0
        if img_topic is not None:
            offset = gt_stamp_offset(first_image_stamp(bag, img_topic), gt_seq, tolerance)
        gt = gt_seq
    else:
        offset = float(stamp_offset)
        img_topic, img_how = None, 'not needed (stamp offset given)'
    items = ((s.stamp_ns / R.NS, s.data, conf.get(s.stamp_ns), infos.get(s.stamp_ns)) for s in depth)
    records, info = _records_from_arrays(items, gt, tolerance=tolerance, stamp_offset=offset)
    info.update({'bag': str(bag), 'depth_topic': d_topic, 'confidence_topic': c_topic, 'info_topic': i_topic,
                 'image_topic': img_topic, 'image_topic_chosen_by': img_how, 'stamp_offset': offset,
                 'depth_messages': len(depth)})
    return records, info


def records_from_export(folder, gt, *, stamp_offset: float = 0.0, tolerance: float = 1e-3
                        ) -> Tuple[List[KeyframeRecord], Dict[str, Any]]:
    """A folder written by ``rosbag_io.export_depth_bag`` (depth/*.png mm, confidence/*.png uint16 scaled by
    65535, stamps_ns.txt or stamps.txt, K.txt) matched by stamp to the GT sequence ``gt``."""
    from dpv_sensor.data.sequence import read_intrinsics
    folder = pathlib.Path(folder)
    files = sorted((folder / 'depth').glob('*.png'))
    if not files:
        raise FileNotFoundError(f'{folder}/depth has no PNG files')
    if (folder / 'stamps_ns.txt').is_file():
        stamps = [int(x) / 1e9 for x in (folder / 'stamps_ns.txt').read_text().split()]
    else:
        stamps = [float(x) for x in (folder / 'stamps.txt').read_text().split()]
    if len(stamps) != len(files):
        raise ValueError(f'{folder}: {len(files)} depth images but {len(stamps)} stamps')
    K = read_intrinsics(folder / 'K.txt') if (folder / 'K.txt').is_file() else None

    def items():
        for f, s in zip(files, stamps):
            raw = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
            d = raw.astype(np.float32) / 1000.0
            d[raw == 0] = np.nan
            cf = folder / 'confidence' / f.name
            c = None
            if cf.is_file():
                c = cv2.imread(str(cf), cv2.IMREAD_UNCHANGED).astype(np.float32) / 65535.0
            yield s, d, c, K
    records, info = _records_from_arrays(items(), gt, tolerance=tolerance, stamp_offset=stamp_offset)
    info['folder'] = str(folder)
    return records, info


def evaluate_records(records: SequenceT[KeyframeRecord], out_dir=None, options: Optional[EvalOptions] = None,
                     *, source: Optional[str] = None, extra: Optional[Dict[str, Any]] = None,
                     name: Optional[str] = None) -> Dict[str, Any]:
    """Score already produced records (from a bag or an export) and write the report to ``out_dir``.

    The GT range is ``options.min_depth / max_depth`` (no estimator to take it from: None = every valid
    GT pixel).
    """
    options = options or EvalOptions()
    acc = score_records(records, min_depth=options.min_depth, max_depth=options.max_depth,
                        occlusion_tol=options.occlusion_tol, progress=options.progress)
    summary = summarize(acc, records, configuration={'options': dataclasses.asdict(options), **(extra or {})},
                        source=source)
    add_consumer_odometry(summary, records, options)
    if out_dir is not None:
        write_report(out_dir, acc, records, summary, montage_frames=options.montage_frames, title=name)
    return summary


# ------------------------------------------------------------------------------------------------------
# offline evaluation
# ------------------------------------------------------------------------------------------------------

def evaluate_offline(sequence, config, *, model=None, pose_refiner=None,
                     max_frames: Optional[int] = None, min_depth: Optional[float] = None,
                     max_depth: Optional[float] = None, keyframes_only: bool = True,
                     keep_outputs: bool = False, input_poses=None) -> Dict[str, Any]:
    """Run a sequence through a :class:`Pipeline` and score every output against the GT depth.

    ``sequence``: anything with ``len``, ``K``, ``image(i)``, ``depth(i)`` (metres, 0 = invalid),
    ``pose(i)`` and ``stamp(i)`` (``data.sequence.Sequence``, the synthetic renderer's sequences).
    Frames are pushed in order with their GT poses, or with ``input_poses[i]`` (T_world_cam per frame, e.g.
    :func:`dpv_sensor.data.trajectory.corrupt_trajectory` of the GT: odometry-like poses). Each output is
    matched to its frame by stamp and scored with ``metrics.MetricAccumulator`` (GT resized with nearest
    neighbour when the output is at the processing size); the GT range defaults to the estimator's depth planes
    [d_min, d_max].

    Returns ``{'rows': [per output: index, stamp, is_keyframe, abs_rel, rmse, delta1, ..., coverage,
    ms_* (median-scaled), ause, mean_confidence, time_ms], 'summary': MetricAccumulator.summary(),
    'status': Pipeline.status (EstimatorStatus), 'outputs': [DepthOutput] (only with keep_outputs)}``.
    Only keyframe outputs are scored unless ``keyframes_only=False``.
    """
    from dpv_sensor.stream.frame import Frame
    from dpv_sensor.stream.pipeline import Pipeline
    pipe = Pipeline(config, model=model, pose_refiner=pose_refiner)
    est = pipe.estimator
    lo = est.d_min if min_depth is None else min_depth
    hi = est.d_max if max_depth is None else max_depth
    acc = M.MetricAccumulator(min_depth=lo, max_depth=hi)
    n = len(sequence) if max_frames is None else min(len(sequence), int(max_frames))
    index_of = {}
    K = np.asarray(sequence.K, dtype=np.float64)
    if input_poses is not None and len(input_poses) < n:
        raise ValueError(f'input_poses has {len(input_poses)} poses for {n} frames')
    outputs = []
    for i in range(n):
        stamp = float(sequence.stamp(i))
        index_of[stamp] = i
        T = sequence.pose(i) if input_poses is None else input_poses[i]
        out = pipe.push(Frame(stamp=stamp, image=sequence.image(i), K_33=K, T_world_cam_44=T, frame_id='camera')).output
        if out is None or (keyframes_only and not out.is_keyframe):
            continue
        j = index_of[out.stamp]
        gt = np.asarray(sequence.depth(j), dtype=np.float32)
        if gt.shape != out.depth_hw.shape:
            gt = cv2.resize(gt, (out.depth_hw.shape[1], out.depth_hw.shape[0]),
                            interpolation=cv2.INTER_NEAREST_EXACT)
        acc.add(out.depth_hw, gt, out.confidence_hw, index=j, stamp=out.stamp, is_keyframe=out.is_keyframe,
                time_ms=out.timings_ms.get('total', float('nan')))
        if keep_outputs:
            outputs.append(out)
    result = {'rows': acc.rows, 'summary': acc.summary(), 'status': pipe.status}
    if keep_outputs:
        result['outputs'] = outputs
    return result
