"""The stream table: every sequence of a data folder and held-out rendered seeds through the node process.

    python -m dpv_sensor.benchmarks.stream_table --data DATA_FOLDER --seeds 50-52 --out out/stream_table \\
        [--noise-seeds 0-2] [--params window_mode=centered ...] [--sequences tum_fr1_rpy ...] [--frames 60]

Each run is one (sequence, pose source, node parameters) replay exactly as ``make demo`` replays
(dpv_sensor.client.replay): the sequence is written as a rosbag2 (image + camera_info at the sequence's stamps,
odometry at 100 Hz), the node is started as its own process at its defaults plus the demo's transport settings
(reliable input, deep queue, diagnostics every 0.1 s) plus ``--params``, the bag is played in lockstep (no image
dropped) while the outputs are recorded, and the recorded bag is scored with ``evaluate bag``'s code
(dpv_sensor.evaluation.offline.records_from_bag / evaluate_records).

``--offline`` runs the same sequences, pose sources and parameters through the node's pipeline in this process
(``evaluation.runner.run_sequence``: no bag, DDS or node process; the honest source's covariance handed to the frames
as the bag would carry it) and scores them the same way, without consumer odometry: a quick ablation that gives the
node's depth (cached and tabled apart, ``offline=True`` in the names). The table of record is the node's.

Pose sources: ``gt`` (the sequence's poses as odometry), ``offset<t>ms`` (``--offset-ms``, default 10: the GT pose
t ms after each image's stamp, a camera-odometry time offset), ``noisy<k>`` for each noise seed k (odometry-like
drift: 2 % of each step's translation in a random direction and a 0.1 deg rotation about a random axis per frame,
chained: dpv_sensor.data.trajectory.corrupt_trajectory) and ``noisy<k>cov`` (``--covariance``: the same poses with the
noise model's own accumulated variance in ``pose.covariance``, as an honest odometry publishes it:
dpv_sensor.data.trajectory.corruption_variance) and ``noisy<k>twist`` (``--twist-covariance``: the same poses with a
constant ``pose.covariance`` and the noise model's motion noise in ``twist.covariance``, as a diff-drive controller
publishes it: dpv_sensor.data.trajectory.corruption_twist_variance). Depth is always scored against the GT depth,
and consumer odometry against the GT poses.

Columns (frame means over the recorded keyframe outputs unless said otherwise):

- abs_rel, d1: metric depth; ms abs_rel: per-frame median-scaled abs_rel; coverage: scored / valid GT pixels.
- ECE, mean conf, d1 pooled, kept@.9, d1@.9, d1@.7: calibration of the published confidence as the probability of
  the delta1 event (dpv_sensor.evaluation.metrics.calibration_summary, pixels pooled over the run); a reliability
  diagram per run in ``OUT/plots/<run>_reliability.png``.
- conf½: confident-half ratio, abs_rel of the most confident half of a frame's scored pixels / abs_rel of all of
  them (dpv_sensor.evaluation.metrics.confident_half_ratio), mean over frames (the pooled figure is in the JSON).
- resets: published outputs whose filter restarted, whichever layer restarted it (the estimator's stream rules,
  an odometry teleport in the pose buffer, lost visual tracking; the filter's own rules are off), the stream's
  first output not counted: the node's ``output_resets`` diagnostics counter; the reasons are in the JSON.
- kf ms: median time of the node's estimator on a keyframe image (from the ``keyframe_ms_last`` values of the
  recorded /diagnostics: one per keyframe, since lockstep waits for the node to report each image).
- const abs_rel, const d1: a constant depth equal to the median GT depth of the whole sequence (an oracle
  constant), scored on the same keyframes and the same pixels as the prediction.
- odo t×, odo r×: consumer odometry (dpv_sensor.evaluation.consumer_odometry): Open3D RGB-D odometry between
  consecutive outputs on the predicted depth vs on the GT depth of the same frames; the ratio of the median
  translation / rotation RPE (hybrid Jacobian, Open3D's default). col t×, col r×: the same with the photometric-only
  Jacobian (the depth only warps), which stays accurate on GT depth where the hybrid one drifts.

Rows ``noisy`` (and ``noisy+cov``) are the mean over the noise seeds (with the spread of abs_rel); each seed's
numbers are in the JSON.

Resumable: every run is cached as ``OUT/runs/<sequence>__<pose>__<params>.json`` and skipped when present (delete a
file to redo that run); rendered seeds are cached under ``OUT/sequences``. Bags live under ``OUT/work/<run>`` while
a run is in progress and are deleted after it (``--keep-bags`` keeps them). The table is rebuilt from every cached
run of the requested set: ``OUT/stream_table.md`` and ``OUT/stream_table.json`` (``stream_table_<params>.*`` with
``--params``); ``--table-only`` only rebuilds it.
SIGINT or SIGTERM (``kill PID``, also for a run started with nohup) stops the run in progress and its node process;
finished runs stay cached. Exit code 0 when every requested run is in the table, 1 when a run failed (the others
still ran), 2 for bad arguments.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import pathlib
import re
import shutil
import sys
import time
import traceback
from dataclasses import dataclass
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

# odometry-like noise of the table's noisy rows: translation error per step (fraction of the step), rotation error
# per frame (deg)
NOISE_TRANS_REL = 0.02
NOISE_ROT_DEG = 0.1
RENDER_FRAMES = 60
RENDER_SIZE = (320, 240)
# the time-offset pose source: the odometry a camera image is paired with describes the pose this much later (ms)
TIME_OFFSET_MS = 10.0
RUN_VERSION = 2   # bump when a cached run's content changes meaning (2: calibration)
# the constant pose covariance of the noisy<k>twist sources (per axis: m^2, rad^2), diff_drive_controller's example
# pose_covariance_diagonal: says nothing about the motion between two poses, the twist covariance does
CONSTANT_POSE_VARIANCE = (1e-3, 1e-3)


# --------------------------------------------------------------------------------------------------------------
# inputs
# --------------------------------------------------------------------------------------------------------------
class PosedView:
    """A sequence with its poses replaced (the odometry a bag is written with); everything else is the sequence's."""

    def __init__(self, seq, poses):
        self._seq = seq
        self._poses = [np.asarray(T, np.float64) for T in poses]
        if len(self._poses) != len(seq):
            raise ValueError(f'{len(self._poses)} poses for a sequence of {len(seq)} frames')

    def __len__(self):
        return len(self._seq)

    def pose(self, i):
        return self._poses[i]

    def __getattr__(self, name):
        return getattr(self._seq, name)


NOISY_SOURCE = re.compile(r'noisy(\d+)(cov|twist)?')


def odometry_poses(seq, pose_source: str) -> List[np.ndarray]:
    """The poses written as odometry for a pose source: 'gt', 'noisy<seed>', 'noisy<seed>cov' or 'noisy<seed>twist'
    (corrupt_trajectory with the table's noise, seeded), or 'offset<ms>' (the GT pose ``ms`` milliseconds after each
    image's stamp, SLERP + linear between frames: a camera-odometry time offset)."""
    gt = [np.asarray(seq.pose(i), np.float64) for i in range(len(seq))]
    if pose_source == 'gt':
        return gt
    m = re.fullmatch(r'offset(\d+(?:\.\d+)?)ms', pose_source)
    if m:
        return time_shifted_poses(seq, gt, float(m.group(1)) / 1000.0)
    m = NOISY_SOURCE.fullmatch(pose_source)
    if not m:
        raise ValueError(f'pose source {pose_source!r} is neither gt, offset<ms>ms, noisy<seed>, noisy<seed>cov nor '
                         'noisy<seed>twist')
    from dpv_sensor.data.trajectory import corrupt_trajectory
    return corrupt_trajectory(gt, trans_noise_rel=NOISE_TRANS_REL, rot_noise_deg=NOISE_ROT_DEG, seed=int(m.group(1)))


def odometry_variance(seq, pose_source: str) -> Optional[np.ndarray]:
    """The pose variance a pose source's odometry publishes (rows per frame: position m^2, rotation rad^2 per
    axis): the noise model's accumulated variance for 'noisy<seed>cov', CONSTANT_POSE_VARIANCE for
    'noisy<seed>twist', None (covariance not filled) otherwise."""
    m = NOISY_SOURCE.fullmatch(pose_source)
    if not (m and m.group(2)):
        return None
    if m.group(2) == 'twist':
        return np.tile(np.asarray(CONSTANT_POSE_VARIANCE, np.float64), (len(seq), 1))
    from dpv_sensor.data.trajectory import corruption_variance
    gt = [np.asarray(seq.pose(i), np.float64) for i in range(len(seq))]
    return corruption_variance(gt, trans_noise_rel=NOISE_TRANS_REL, rot_noise_deg=NOISE_ROT_DEG)


def odometry_twist_variance(seq, pose_source: str) -> Optional[np.ndarray]:
    """The twist variance a pose source's odometry publishes (rows per frame: linear m^2/s, angular rad^2/s per
    axis): the noise model's motion noise as rates for 'noisy<seed>twist' (corruption_twist_variance), None (not
    filled) otherwise."""
    m = NOISY_SOURCE.fullmatch(pose_source)
    if not (m and m.group(2) == 'twist'):
        return None
    from dpv_sensor.data.trajectory import corruption_twist_variance
    gt = [np.asarray(seq.pose(i), np.float64) for i in range(len(seq))]
    return corruption_twist_variance(gt, [float(seq.stamp(i)) for i in range(len(seq))],
                                     trans_noise_rel=NOISE_TRANS_REL, rot_noise_deg=NOISE_ROT_DEG)


def time_shifted_poses(seq, poses: List[np.ndarray], offset_s: float) -> List[np.ndarray]:
    """The trajectory ``poses`` (one per frame, at ``seq.stamp(i)``) evaluated ``offset_s`` seconds after each frame's
    stamp (SLERP + linear between the two frames around it, held at the ends)."""
    from dpv_sensor.core.geometry import interpolate_pose
    stamps = np.array([float(seq.stamp(i)) for i in range(len(seq))], np.float64)
    out = []
    for t in stamps + float(offset_s):
        j = int(np.searchsorted(stamps, t, side='right'))
        if j <= 0:
            out.append(poses[0].copy())
        elif j >= len(stamps):
            out.append(poses[-1].copy())
        else:
            a = (t - stamps[j - 1]) / (stamps[j] - stamps[j - 1])
            out.append(interpolate_pose(poses[j - 1], poses[j], float(a)))
    return out


def sequence_folders(data: pathlib.Path) -> List[pathlib.Path]:
    """Every sequence folder (one with poses.txt and K.txt) directly under `data`, sorted by name."""
    return sorted(p for p in data.iterdir() if p.is_dir() and (p / 'poses.txt').is_file() and (p / 'K.txt').is_file())


def rendered_sequence(out: pathlib.Path, seed: int, frames: int, progress: bool,
                      size: Tuple[int, int] = RENDER_SIZE) -> pathlib.Path:
    """The held-out rendered scene `seed` as a sequence folder under OUT/sequences (rendered once; rendered again
    when the frame count or the size asked for differ)."""
    folder = out / 'sequences' / f'synthetic_seed{seed}'
    done = folder / '.complete'
    tag = f'{frames} {size[0]}x{size[1]}'
    if done.is_file() and done.read_text().strip() == tag:
        return folder
    from dpv_sensor.client.replay import render_scene
    if folder.exists():
        shutil.rmtree(folder)
    render_scene(folder, seed, frames, size[0], size[1], progress)
    done.write_text(tag)
    return folder


def params_tag(params: Dict[str, Any]) -> str:
    """A file-name-safe name of the --params overrides ('defaults' without any)."""
    if not params:
        return 'defaults'
    text = ','.join(f'{k}={params[k]}' for k in sorted(params))
    return re.sub(r'[^A-Za-z0-9=,._-]+', '_', text)


def run_key(seq_name: str, pose_source: str, params: Dict[str, Any]) -> str:
    return f'{seq_name}__{pose_source}__{params_tag(params)}'


# --------------------------------------------------------------------------------------------------------------
# scoring helpers
# --------------------------------------------------------------------------------------------------------------
def oracle_constant(seq, min_depth=None, max_depth=None) -> float:
    """Median of every valid GT depth of the sequence (within the scored range)."""
    from dpv_sensor.evaluation.metrics import gt_valid_mask
    vals = []
    for i in range(len(seq)):
        d = np.asarray(seq.depth(i), np.float32)
        vals.append(d[gt_valid_mask(d, min_depth, max_depth)])
    allv = np.concatenate(vals) if vals else np.zeros(0)
    return float(np.median(allv)) if allv.size else float('nan')


def constant_on_same_pixels(records, constant: float, min_depth=None, max_depth=None) -> Dict[str, Any]:
    """A constant depth scored on the records' keyframes and exactly the pixels their predictions are scored on."""
    from dpv_sensor.evaluation.metrics import MetricAccumulator
    acc = MetricAccumulator(min_depth=min_depth, max_depth=max_depth)
    for r in records:
        pred = np.where(np.isfinite(r.depth_hw), np.float32(constant), np.float32(np.nan))
        acc.add(pred, r.gt_depth_hw)
    fm = acc.summary()['metric']['frame_mean']
    return {'constant_m': constant, 'abs_rel': fm['abs_rel'], 'delta1': fm['delta1'], 'rmse': fm['rmse']}


def diagnostics_series(output_bag) -> List[Dict[str, str]]:
    """The node's /diagnostics values ({key: str}) recorded in the output bag, in record order."""
    from dpv_sensor.data import rosbag_io as R
    from dpv_sensor.client.replay import DIAGNOSTICS_SUFFIX
    out = []
    if '/diagnostics' not in R.bag_topics(output_bag):
        return out
    for _t, _ty, _log, msg in R.read_messages(output_bag, ['/diagnostics']):
        for st in msg.status:
            if st.name.endswith(DIAGNOSTICS_SUFFIX) and st.hardware_id.startswith('dpv_sensor'):
                out.append({kv.key: kv.value for kv in st.values})
    return out


def keyframe_times_ms(series: List[Dict[str, str]]) -> Dict[int, float]:
    """Estimator time of each keyframe image: {keyframe count: keyframe_ms_last} from the recorded diagnostics."""
    from dpv_sensor.client.replay import _as_number
    out: Dict[int, float] = {}
    for v in series:
        k = _as_number(v.get('estimator_keyframes'))
        ms = _as_number(v.get('keyframe_ms_last'))
        if isinstance(k, int) and k > 0 and isinstance(ms, (int, float)):
            out.setdefault(k, float(ms))
    return out


def reset_reasons(series: List[Dict[str, str]]) -> List[str]:
    """The distinct `last_output_reset` values in the order they appeared (one per counted output reset, as long
    as two resets are not reported by the same diagnostics message)."""
    out: List[str] = []
    for v in series:
        r = v.get('last_output_reset') or ''
        if r and (not out or out[-1] != r):
            out.append(r)
    return out


def _f(v):
    return v if isinstance(v, (int, float)) and not (isinstance(v, float) and not math.isfinite(v)) else None


def _get(d, *path):
    for p in path:
        if not isinstance(d, dict) or p not in d:
            return None
        d = d[p]
    return d


# --------------------------------------------------------------------------------------------------------------
# one run
# --------------------------------------------------------------------------------------------------------------
def noise_description(pose_source: str) -> Optional[Dict[str, float]]:
    """What was done to the GT poses of a pose source (None for gt)."""
    if pose_source == 'gt':
        return None
    m = re.fullmatch(r'offset(\d+(?:\.\d+)?)ms', pose_source)
    if m:
        return {'time_offset_ms': float(m.group(1))}
    m = NOISY_SOURCE.fullmatch(pose_source)
    published = m.group(2) if m else None
    return {'trans_rel': NOISE_TRANS_REL, 'rot_deg_per_frame': NOISE_ROT_DEG,
            'covariance': published == 'cov', 'twist_covariance': published == 'twist'}


def run_one(seq_name: str, seq_dir: pathlib.Path, pose_source: str, user_params: Dict[str, Any],
            out: pathlib.Path, *, min_depth=None, max_depth=None, keep_bags: bool = False, progress: bool = True,
            start_timeout: float = 180.0, frame_timeout: float = 180.0,
            consumer_odometry: bool = True) -> Dict[str, Any]:
    """Replay one sequence with one pose source through the node and score it; returns the run's JSON dict
    (``consumer_odometry`` False: without the Open3D odometry check, which is most of the scoring time on long
    sequences)."""
    from dpv_sensor.evaluation import offline as E
    from dpv_sensor.data import rosbag_io as R
    from dpv_sensor.data.sequence import Sequence
    from dpv_sensor.client import replay as D

    key = run_key(seq_name, pose_source, user_params)
    work = out / 'work' / key
    if work.exists():
        shutil.rmtree(work)
    (work / 'logs').mkdir(parents=True)
    input_bag, output_bag = work / 'input_bag', work / 'output_bag'
    params = dict(D.DEMO_NODE_PARAMS)
    params.update(user_params)
    timing: Dict[str, float] = {}
    t_all = time.perf_counter()

    seq = Sequence(seq_dir)
    t = time.perf_counter()
    odom = PosedView(seq, odometry_poses(seq, pose_source))
    bs = R.write_sequence_bag(input_bag, odom, odom_rate=D.ODOM_RATE_HZ,
                              pose_variance=odometry_variance(seq, pose_source),
                              twist_variance=odometry_twist_variance(seq, pose_source), progress=progress)
    timing['bag_s'] = round(time.perf_counter() - t, 1)

    steps = D.Steps(3)
    topics = {'image': R.IMAGE_TOPIC, 'camera_info': R.CAMERA_INFO_TOPIC, 'odom': R.ODOM_TOPIC}
    t = time.perf_counter()
    replay = D.run_node_replay(steps, input_bag, output_bag, topics=topics, params=params, log_dir=work / 'logs',
                               lockstep=True, rate=1.0, start_timeout=start_timeout, frame_timeout=frame_timeout,
                               max_images=0, progress=progress)
    timing['node_s'] = round(time.perf_counter() - t, 1)
    d = replay.diagnostics

    t = time.perf_counter()
    records, info = E.records_from_bag(output_bag, seq_dir)
    if not records:
        raise RuntimeError(f'no recorded depth image matched a GT frame ({info})')
    options = E.EvalOptions(min_depth=min_depth, max_depth=max_depth, progress=progress,
                            consumer_odometry=consumer_odometry).validate()
    summary = E.evaluate_records(records, None, options, source=str(output_bag), extra={'input': info})
    constant = constant_on_same_pixels(records, oracle_constant(seq, min_depth, max_depth), min_depth, max_depth)
    series = diagnostics_series(output_bag)
    kf_ms = keyframe_times_ms(series)
    timing['score_s'] = round(time.perf_counter() - t, 1)
    timing['total_s'] = round(time.perf_counter() - t_all, 1)

    if summary.get('calibration'):
        from dpv_sensor.evaluation import plots
        plots.reliability_plot({f'{seq_name} {pose_source}': summary['calibration']},
                               out / 'plots' / f'{key}_reliability.png', title=f'{seq_name}, poses {pose_source}')
    co = summary.get('consumer_odometry') or {}
    kf_vals = list(kf_ms.values())
    result = {
        'version': RUN_VERSION, 'key': key, 'sequence': seq_name, 'sequence_folder': str(seq_dir),
        'pose_source': pose_source, 'params': user_params, 'node_parameters': params,
        'noise': noise_description(pose_source),
        'frames': len(seq), 'size': list(seq.size) if hasattr(seq, 'size') else None,
        'keyframes_scored': len(records),
        'abs_rel': summary['metric']['frame_mean']['abs_rel'],
        'delta1': summary['metric']['frame_mean']['delta1'],
        'rmse': summary['metric']['frame_mean']['rmse'],
        'ms_abs_rel': summary['median_scaled']['frame_mean']['abs_rel'],
        'coverage': summary['coverage']['frame_mean'],
        'confident_half_ratio': _get(summary, 'confidence', 'confident_half_ratio_frame_mean'),
        'confident_half_ratio_pooled': _get(summary, 'confidence', 'confident_half_ratio_pooled'),
        'ause': _get(summary, 'confidence', 'ause_frame_mean'),
        'mean_confidence': _get(summary, 'confidence', 'mean_confidence'),
        'calibration': summary.get('calibration'),
        'temporal': _get(summary, 'temporal_consistency', 'pair_mean'),
        'output_resets': int(D._as_number(d.get('output_resets'), -1)),
        'output_reset_reasons': reset_reasons(series),
        'estimator_resets': D._as_number(d.get('filter_resets')),
        'last_estimator_reset_reason': d.get('last_reset_reason') or '',
        'keyframe_ms_median': float(np.median(kf_vals)) if kf_vals else None,
        'keyframe_ms_mean': float(np.mean(kf_vals)) if kf_vals else None,
        'keyframes_timed': len(kf_vals),
        'node_keyframe_ms_median_last50': D._as_number(d.get('keyframe_ms_median')),
        'node_processing_ms_median': D._as_number(d.get('processing_ms_median')),
        'constant': constant,
        'consumer_odometry': co,
        'consumer_ratio_trans': co.get('ratio_trans'),
        'consumer_ratio_rot': co.get('ratio_rot'),
        'node': {'images_in_bag': replay.images_in_bag, 'images_sent': replay.images_sent,
                 'frames_received': d.get('frames_received'), 'frames_processed': d.get('frames_processed'),
                 'keyframes': d.get('estimator_keyframes'), 'outputs_published': d.get('outputs_published'),
                 'recorded': replay.recorded, 'dropped_total': d.get('dropped_total'),
                 'faults': {k[7:]: v for k, v in d.items() if k.startswith('faults.')},
                 'measurement_model': d.get('measurement_model'), 'measurement_reason': d.get('measurement_reason'),
                 'filter_mode': d.get('filter_mode'), 'device': d.get('device'), 'precision': d.get('precision'),
                 'pose_uncertainty': d.get('pose_uncertainty'),
                 'exit_code': replay.node_exit_code, 'peak_rss_mib': replay.node_peak_rss_mib,
                 'command': replay.node_command, 'warnings': replay.warnings},
        'bag': {'frames': bs.frames, 'odometry': bs.odometry, 'duration_s': bs.duration_s},
        'matching': info, 'min_depth': min_depth, 'max_depth': max_depth,
        'timing': timing, 'finished': time.strftime('%Y-%m-%d %H:%M:%S'),
    }
    if not keep_bags:
        shutil.rmtree(work, ignore_errors=True)
    return E.to_jsonable(result)


def run_one_offline(seq_name: str, seq_dir: pathlib.Path, pose_source: str, user_params: Dict[str, Any],
                    out: pathlib.Path, *, min_depth=None, max_depth=None, progress: bool = True) -> Dict[str, Any]:
    """``--offline``: the same sequence, pose source and parameters through the node's pipeline in this process
    (evaluation.runner.run_sequence: no bag, no DDS, no node), scored the same way; the run's JSON dict with the
    columns the table shows (no consumer odometry). Quick ablations; the table of record is the node's."""
    from dpv_sensor.evaluation import offline as E
    from dpv_sensor.evaluation import runner as RN
    from dpv_sensor.data.sequence import Sequence
    key = run_key(seq_name, pose_source, dict(user_params, offline=True))     # cached and tabled apart
    t_all = time.perf_counter()
    seq = Sequence(seq_dir)
    config, values = RN.build_config(user_params)
    records, _ = RN.run_sequence(seq, config, E.EvalOptions(progress=progress), keep_images=False,
                                 poses=odometry_poses(seq, pose_source),
                                 pose_variance=odometry_variance(seq, pose_source),
                                 twist_variance=odometry_twist_variance(seq, pose_source))
    if not records:
        raise RuntimeError('the pipeline published no keyframe depth')
    options = E.EvalOptions(min_depth=min_depth, max_depth=max_depth, progress=progress,
                            consumer_odometry=False).validate()
    summary = E.evaluate_records(records, None, options, source='offline')
    times = [r.time_ms for r in records if math.isfinite(r.time_ms)]
    resets = [r.reset_reason for r in records[1:] if r.reset_reason]
    return E.to_jsonable({
        'version': RUN_VERSION, 'key': key, 'sequence': seq_name, 'sequence_folder': str(seq_dir),
        'pose_source': pose_source, 'params': user_params, 'node_parameters': values, 'offline': True,
        'noise': noise_description(pose_source), 'frames': len(seq), 'keyframes_scored': len(records),
        'abs_rel': summary['metric']['frame_mean']['abs_rel'], 'delta1': summary['metric']['frame_mean']['delta1'],
        'rmse': summary['metric']['frame_mean']['rmse'],
        'ms_abs_rel': summary['median_scaled']['frame_mean']['abs_rel'],
        'coverage': summary['coverage']['frame_mean'],
        'confident_half_ratio': _get(summary, 'confidence', 'confident_half_ratio_frame_mean'),
        'mean_confidence': _get(summary, 'confidence', 'mean_confidence'),
        'calibration': summary.get('calibration'),
        'output_resets': len(resets), 'output_reset_reasons': resets,
        'keyframe_ms_median': float(np.median(times)) if times else None,
        'constant': constant_on_same_pixels(records, oracle_constant(seq, min_depth, max_depth), min_depth,
                                            max_depth),
        'min_depth': min_depth, 'max_depth': max_depth,
        'timing': {'total_s': round(time.perf_counter() - t_all, 1)}, 'finished': time.strftime('%Y-%m-%d %H:%M:%S'),
    })


# --------------------------------------------------------------------------------------------------------------
# the table
# --------------------------------------------------------------------------------------------------------------
COLUMNS = [   # (header, run key, format)
    ('kf', 'keyframes_scored', '{:d}'),
    ('abs_rel', 'abs_rel', '{:.3f}'),
    ('d1', 'delta1', '{:.3f}'),
    ('ms abs_rel', 'ms_abs_rel', '{:.3f}'),
    ('conf½', 'confident_half_ratio', '{:.2f}'),
    ('ECE', ('calibration', 'ece'), '{:.3f}'),
    ('mean conf', ('calibration', 'mean_confidence'), '{:.2f}'),
    ('d1 pooled', ('calibration', 'hit_rate'), '{:.2f}'),
    ('kept@.9', ('calibration', 'kept', '0.9', 'share'), '{:.2f}'),
    ('d1@.9', ('calibration', 'kept', '0.9', 'delta1'), '{:.2f}'),
    ('d1@.7', ('calibration', 'kept', '0.7', 'delta1'), '{:.2f}'),
    ('coverage', 'coverage', '{:.3f}'),
    ('resets', 'output_resets', '{:g}'),
    ('kf ms', 'keyframe_ms_median', '{:.0f}'),
    ('const abs_rel', ('constant', 'abs_rel'), '{:.3f}'),
    ('const d1', ('constant', 'delta1'), '{:.3f}'),
    ('odo t×', 'consumer_ratio_trans', '{:.2f}'),
    ('odo r×', 'consumer_ratio_rot', '{:.2f}'),
    ('col t×', ('consumer_odometry', 'color', 'ratio_trans'), '{:.2f}'),
    ('col r×', ('consumer_odometry', 'color', 'ratio_rot'), '{:.2f}'),
]


def _value(run: Dict[str, Any], key):
    return _f(_get(run, *key) if isinstance(key, tuple) else run.get(key))


def table_rows(runs: List[Dict[str, Any]], sequences: List[str], noise_seeds: List[int],
               params: Dict[str, Any], single_sources: Tuple[str, ...] = ('gt',)) -> List[Dict[str, Any]]:
    """One row per sequence and pose source (each of ``single_sources``, e.g. 'gt' and 'offset10ms'; 'noisy' = mean
    over the noise seeds that have run)."""
    by_key = {r['key']: r for r in runs}
    rows = []
    for s in sequences:
        for src in single_sources:
            one = by_key.get(run_key(s, src, params))
            if one is not None:
                rows.append({'sequence': s, 'poses': src, 'runs': 1,
                             **{h: _value(one, k) for h, k, _f_ in COLUMNS}})
        for suffix, label in (('', 'noisy'), ('cov', 'noisy+cov'), ('twist', 'noisy+twist cov')):
            noisy = [by_key[run_key(s, f'noisy{k}{suffix}', params)] for k in noise_seeds
                     if run_key(s, f'noisy{k}{suffix}', params) in by_key]
            if noisy:
                rows.append(_mean_row(s, f'{label} ×{len(noisy)}', noisy))
    return rows


def _mean_row(sequence: str, poses: str, noisy: List[Dict[str, Any]]) -> Dict[str, Any]:
    """One table row: the mean of the columns over the runs of several noise seeds (resets: their total; the
    spread of abs_rel)."""
    row = {'sequence': sequence, 'poses': poses, 'runs': len(noisy)}
    for h, k, _ in COLUMNS:
        vals = [v for v in (_value(r, k) for r in noisy) if v is not None]
        row[h] = float(np.mean(vals)) if vals else None
    if row['resets'] is not None:      # resets: the total over the seeds
        row['resets'] = int(sum(_value(r, 'output_resets') or 0 for r in noisy))
    ab = [v for v in (_value(r, 'abs_rel') for r in noisy) if v is not None]
    row['abs_rel_range'] = [min(ab), max(ab)] if ab else None
    return row


def markdown(rows: List[Dict[str, Any]]) -> str:
    heads = ['sequence', 'poses'] + [h for h, _k, _f in COLUMNS]
    fmts = {h: f for h, _k, f in COLUMNS}
    lines = ['| ' + ' | '.join(heads) + ' |', '|' + '|'.join(['---'] * 2 + ['---:'] * len(COLUMNS)) + '|']
    for r in rows:
        cells = [r['sequence'], r['poses']]
        for h in heads[2:]:
            v = r.get(h)
            if v is None:
                cells.append('-')
                continue
            if h == 'kf' and r['runs'] > 1:
                cells.append(f'{v:.0f}')
            else:
                cells.append(fmts[h].format(int(v) if fmts[h] == '{:d}' else v))
            if h == 'abs_rel' and r.get('abs_rel_range'):
                lo, hi = r['abs_rel_range']
                if hi - lo >= 0.0005:
                    cells[-1] += f' ({lo:.3f}–{hi:.3f})'
        lines.append('| ' + ' | '.join(cells) + ' |')
    return '\n'.join(lines)


LEGEND = ('Frame means over the keyframe outputs recorded from the node (lockstep replay: the node drops no image '
          'once it has its first camera_info; the drops are listed per run below). '
          "poses: gt = the sequence's poses as odometry; offset<t>ms = the GT pose t ms after each image stamp (a "
          'camera-odometry time offset); noisy ×n = mean over n odometry noise seeds (2 % of each '
          'step, 0.1°/frame rotation random walk; abs_rel range over the seeds in brackets); noisy+cov = the same '
          "odometry publishing the noise model's accumulated variance in pose.covariance; noisy+twist cov = the same "
          "odometry publishing a constant pose.covariance and the noise model's motion noise in twist.covariance (a "
          'diff-drive controller). ms = median-scaled. '
          "conf½ = abs_rel of the most confident half of each frame's pixels / abs_rel of all. ECE = expected "
          'calibration error of the confidence against the event "true depth within ×1.25" (10 bins, pixels pooled '
          'over the run); mean conf vs d1 pooled = the same two averages over all pooled pixels; kept@.9 / d1@.9 = '
          'share of pixels with confidence >= 0.9 and their d1 (d1@.7 at 0.7). resets = outputs '
          'whose filter restarted (first output not counted; summed over the seeds). kf ms = median estimator time '
          "per keyframe image in the node. const = the sequence's median GT depth as a constant, on the same "
          'keyframes and pixels. odo t× / r× = Open3D RGB-D odometry (hybrid) between consecutive outputs: median '
          'translation / rotation RPE on predicted depth ÷ on GT depth; col t× / r×: the same with the '
          'photometric-only (color) Jacobian, steadier where the hybrid one drifts even on GT depth.')


def run_details(runs: List[Dict[str, Any]]) -> str:
    """Per run: frames, keyframes scored, images dropped, time (bag / node replay / scoring), the reset reasons."""
    lines = ['| run | frames | keyframes | dropped | min (bag + node + scoring) | resets |',
             '|---|---:|---:|---:|---|---|']
    for r in runs:
        t = r.get('timing') or {}
        mins = ' + '.join(f'{(t.get(k) or 0) / 60:.1f}' for k in ('bag_s', 'node_s', 'score_s'))
        reasons = '; '.join(r.get('output_reset_reasons') or []) or '-'
        lines.append(f"| {r['sequence']} {r['pose_source']} | {r.get('frames')} | {r.get('keyframes_scored')} | "
                     f"{_get(r, 'node', 'dropped_total')} | {(t.get('total_s') or 0) / 60:.1f} ({mins}) | {reasons} |")
    return '\n'.join(lines)


def write_table(out: pathlib.Path, runs, sequences, noise_seeds, params, command: str,
                failures: Dict[str, str], single_sources: Tuple[str, ...] = ('gt',),
                covariance: bool = False, twist: bool = False) -> Tuple[str, Dict[str, Any]]:
    rows = table_rows(runs, sequences, noise_seeds, params, single_sources)
    md = markdown(rows)
    done = len(runs)
    wanted = len(sequences) * (len(single_sources) + len(noise_seeds) * (1 + int(covariance) + int(twist)))
    times = [r['timing']['total_s'] for r in runs if _get(r, 'timing', 'total_s') is not None]
    head = (f'Command: `{command}`\n\nParameters: {params_tag(params)}; {done} of {wanted} runs done'
            + (f', {len(failures)} failed' if failures else '')
            + (f'; {sum(times) / 60:.0f} min of runs (median {np.median(times) / 60:.1f} min per run)' if times
               else '') + '.')
    text = head + '\n\n' + md + '\n\n' + LEGEND + '\n\n' + run_details(runs) + '\n'
    if failures:
        text += '\nFailed runs:\n' + ''.join(f'- {k}: {v}\n' for k, v in failures.items())
    (out / f'stream_table{_suffix(params)}.md').write_text(text)
    data = {'command': command, 'params': params, 'sequences': sequences, 'noise_seeds': noise_seeds,
            'rows': rows, 'runs': {r['key']: r for r in runs}, 'failures': failures}
    from dpv_sensor.evaluation.offline import to_jsonable
    with open(out / f'stream_table{_suffix(params)}.json', 'w') as fh:
        json.dump(to_jsonable(data), fh, indent=1)
    return text, data


def _suffix(params: Dict[str, Any]) -> str:
    return '' if not params else '_' + params_tag(params)


# --------------------------------------------------------------------------------------------------------------
# main
# --------------------------------------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog='stream_table', description=__doc__.split('\n\n')[0],
                                epilog=__doc__.split('\n\n', 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--data', default=None, help='folder of sequence folders (every one is replayed)')
    p.add_argument('--sequences', nargs='*', default=None, help='only these sequence folders of --data')
    p.add_argument('--seeds', default='50-52', help="held-out rendered seeds, e.g. '50-52' or '50,53' ('' for none)")
    p.add_argument('--frames', type=int, default=RENDER_FRAMES, help=f'frames per rendered seed ({RENDER_FRAMES})')
    p.add_argument('--render-size', default=f'{RENDER_SIZE[0]}x{RENDER_SIZE[1]}', metavar='WxH',
                   help=f'size of the rendered seeds ({RENDER_SIZE[0]}x{RENDER_SIZE[1]})')
    p.add_argument('--noise-seeds', default='0-2', help="odometry noise seeds ('' for GT poses only)")
    p.add_argument('--covariance', action='store_true',
                   help='add the honest-odometry pose sources noisy<k>cov: the noisy poses of every noise seed with '
                        "the noise model's accumulated variance in pose.covariance")
    p.add_argument('--twist-covariance', action='store_true',
                   help='add the diff-drive pose sources noisy<k>twist: the noisy poses of every noise seed with a '
                        "constant pose.covariance and the noise model's motion noise in twist.covariance")
    p.add_argument('--no-gt', action='store_true', help='only the noisy (and time-offset) pose sources')
    p.add_argument('--offset-ms', type=float, default=TIME_OFFSET_MS,
                   help=f'add the time-offset pose source: GT poses taken this many ms after each image stamp '
                        f'({TIME_OFFSET_MS:g}; 0 = none)')
    p.add_argument('--params', nargs='*', default=[], metavar='KEY=VALUE', help='node parameters over the defaults')
    p.add_argument('--out', default='out/stream_table', help='output folder (cache of runs, tables)')
    p.add_argument('--min-depth', type=float, default=None, help='smallest GT depth scored (default: all valid)')
    p.add_argument('--max-depth', type=float, default=None, help='largest GT depth scored (default: all valid)')
    p.add_argument('--domain-id', type=int, default=None,
                   help='ROS_DOMAIN_ID of the node and the player (default: $ROS_DOMAIN_ID, else a random one)')
    p.add_argument('--keep-bags', action='store_true', help='keep the input / output bags of every run')
    p.add_argument('--no-consumer-odometry', action='store_true',
                   help='skip the consumer check (Open3D RGB-D odometry on predicted vs GT depth: the odo/col '
                        'columns), most of the scoring time on long sequences')
    p.add_argument('--table-only', action='store_true', help='run nothing, rebuild the table from the cache')
    p.add_argument('--offline', action='store_true',
                   help="the node's pipeline in this process (no bag, DDS or node; no consumer odometry): quick "
                        "ablations, cached and tabled apart (offline=True in the names)")
    p.add_argument('--quiet', action='store_true', help='no progress bars')
    return p


@dataclass
class _Options:
    """The command line's values that need parsing: node parameters, rendered and noise seeds, render size."""
    params: Dict[str, Any]
    seeds: List[int]
    noise_seeds: List[int]
    render_size: Tuple[int, int]


@dataclass
class _Table:
    """What one invocation covers: the sequences (name -> folder; None: a rendered seed, rendered when its first run
    starts), the pose sources, the node parameters, and where the runs are cached and the table is written."""
    out: pathlib.Path
    params: Dict[str, Any]
    folders: Dict[str, Optional[pathlib.Path]]
    noise_seeds: List[int]
    single_sources: Tuple[str, ...]      # pose sources with one run per sequence (gt, offset<t>ms)
    command: str
    covariance: bool = False             # also the noisy<k>cov sources (the noise model's variance published)
    twist: bool = False                  # also the noisy<k>twist sources (constant pose, motion noise in the twist)
    offline: bool = False                # the pipeline in this process instead of the node (run_one_offline)

    @property
    def tag_params(self) -> Dict[str, Any]:
        """The parameters as run files and table names carry them (offline runs are told apart)."""
        return dict(self.params, offline=True) if self.offline else self.params

    @property
    def sequences(self) -> List[str]:
        return list(self.folders)

    @property
    def sources(self) -> List[str]:
        suffixes = ('',) + (('cov',) if self.covariance else ()) + (('twist',) if self.twist else ())
        return list(self.single_sources) + [f'noisy{k}{x}' for x in suffixes for k in self.noise_seeds]

    def run_file(self, seq_name: str, pose_source: str) -> pathlib.Path:
        return self.out / 'runs' / f'{run_key(seq_name, pose_source, self.tag_params)}.json'

    def cached_runs(self) -> List[Dict[str, Any]]:
        """The cached runs of this table (of the current RUN_VERSION), sequence by sequence."""
        runs = []
        for s in self.sequences:
            for src in self.sources:
                f = self.run_file(s, src)
                if f.is_file():
                    r = json.loads(f.read_text())
                    if r.get('version') == RUN_VERSION:
                        r['key'] = f.stem      # the file's name is the key (offline runs once kept the node's)
                        runs.append(r)
        return runs

    def write(self, failures: Dict[str, str]) -> str:
        """Write the table of the cached runs; its text."""
        text, _ = write_table(self.out, self.cached_runs(), self.sequences, self.noise_seeds, self.tag_params,
                              self.command, failures, self.single_sources, self.covariance, self.twist)
        return text


def _parse_options(ap: argparse.ArgumentParser, a) -> _Options:
    """Parse --params, --seeds, --noise-seeds and --render-size (a usage error names a bad one)."""
    from dpv_sensor.client.replay import parse_params
    from dpv_sensor.training.dataset import check_heldout_seeds, parse_seeds
    try:
        params = parse_params(a.params)
        seeds = check_heldout_seeds(parse_seeds(a.seeds))
        noise_seeds = list(parse_seeds(a.noise_seeds))
        m = re.fullmatch(r'(\d+)x(\d+)', a.render_size)
        if not m:
            raise ValueError(f'--render-size expects WxH, got {a.render_size!r}')
        render_size = (int(m.group(1)), int(m.group(2)))
    except ValueError as exc:
        ap.error(str(exc))
    return _Options(params=params, seeds=seeds, noise_seeds=noise_seeds, render_size=render_size)


def _sequences(ap: argparse.ArgumentParser, a, seeds: List[int]) -> Dict[str, Optional[pathlib.Path]]:
    """The folders of --data (only --sequences when given), then the rendered seeds (None: not rendered yet)."""
    folders: Dict[str, Optional[pathlib.Path]] = {}
    if a.data:
        data = pathlib.Path(a.data)
        if not data.is_dir():
            ap.error(f'--data {data}: no such folder')
        found = {f.name: f.resolve() for f in sequence_folders(data)}
        names = a.sequences if a.sequences is not None else sorted(found)
        missing = [n for n in names if n not in found]
        if missing:
            ap.error(f'no sequence folder {missing} in {data} (found: {sorted(found)})')
        folders.update({n: found[n] for n in names})
    for s in seeds:
        folders[f'synthetic_seed{s}'] = None
    if not folders:
        ap.error('nothing to run: give --data and/or --seeds')
    return folders


def _prepare_to_run(out: pathlib.Path, domain_id: Optional[int]) -> None:
    """SIGINT and SIGTERM stop the current run cleanly (its node process included), also when the benchmark was
    started in the background, where the shell leaves SIGINT ignored; finished runs stay cached. The runs get a
    private ROS environment under `out` (``domain_id``, else $ROS_DOMAIN_ID, else a random domain)."""
    import signal
    from dpv_sensor.client.ros_io import private_ros_env

    def _stop(signum, frame):
        raise KeyboardInterrupt
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, _stop)
    if domain_id is None and os.environ.get('ROS_DOMAIN_ID', '').isdigit():
        domain_id = int(os.environ['ROS_DOMAIN_ID'])
    private_ros_env(out, domain_id)


def _run_missing(table: _Table, a, render_size: Tuple[int, int], failures: Dict[str, str]) -> bool:
    """Run what is not cached yet (every sequence with GT poses first), caching each run and rewriting the table
    after it; a failed run is noted in `failures`. False when interrupted."""
    progress = not a.quiet
    todo = [(s, src) for src in table.sources for s in table.sequences if not table.run_file(s, src).is_file()]
    print(f'stream table: {len(table.sequences) * len(table.sources) - len(todo)} runs cached, {len(todo)} to run '
          f'(parameters: {params_tag(table.params)}) -> {table.out}', flush=True)
    for n, (s, src) in enumerate(todo, 1):
        key = run_key(s, src, table.tag_params)
        print(f'\n=== run {n}/{len(todo)}: {s}, poses {src}, {params_tag(table.params)} '
              f'({time.strftime("%H:%M:%S")}) ===', flush=True)
        try:
            if table.folders[s] is None:
                table.folders[s] = rendered_sequence(table.out, int(s[len('synthetic_seed'):]), a.frames, progress,
                                                     render_size)
            if table.offline:
                res = run_one_offline(s, table.folders[s], src, table.params, table.out, min_depth=a.min_depth,
                                      max_depth=a.max_depth, progress=progress)
            else:
                res = run_one(s, table.folders[s], src, table.params, table.out, min_depth=a.min_depth,
                              max_depth=a.max_depth, keep_bags=a.keep_bags, progress=progress,
                              consumer_odometry=not a.no_consumer_odometry)
        except KeyboardInterrupt:
            print('\ninterrupted; finished runs are cached, run the same command again to go on', flush=True)
            return False
        except Exception as exc:
            failures[key] = f'{type(exc).__name__}: {exc}'
            (table.out / 'runs' / f'{key}.error.txt').write_text(traceback.format_exc())
            print(f'run {key} FAILED: {failures[key]}', flush=True)
            continue
        _cache_run(table.run_file(s, src), res)
        print(f"run {key}: abs_rel {res['abs_rel']:.4f}, d1 {res['delta1']:.3f}, {res['keyframes_scored']} "
              f"keyframes, resets {res['output_resets']}, kf {res['keyframe_ms_median'] or float('nan'):.0f} ms, "
              f"{res['timing']['total_s']:.0f} s", flush=True)
        table.write(failures)
    return True


def _cache_run(path: pathlib.Path, res: Dict[str, Any]) -> None:
    """Write a run's result to the cache (through a temporary file: an interrupted write leaves no run)."""
    tmp = path.with_name(path.name + '.tmp')
    tmp.write_text(json.dumps(res, indent=1))
    tmp.replace(path)


def main(argv: Optional[List[str]] = None) -> int:
    from dpv_sensor.cli import tool_argv
    argv = tool_argv(argv)
    ap = build_parser()
    a = ap.parse_args(argv)
    opts = _parse_options(ap, a)
    out = pathlib.Path(a.out).resolve()
    (out / 'runs').mkdir(parents=True, exist_ok=True)
    folders = _sequences(ap, a, opts.seeds)
    single = tuple(([] if a.no_gt else ['gt']) + ([f'offset{a.offset_ms:g}ms'] if a.offset_ms > 0 else []))
    table = _Table(out=out, params=opts.params, folders=folders, noise_seeds=opts.noise_seeds, single_sources=single,
                   command='python -m dpv_sensor.benchmarks.stream_table ' +
                   ' '.join(x for x in argv if x != '--table-only'), covariance=a.covariance, twist=a.twist_covariance,
                   offline=a.offline)
    failures: Dict[str, str] = {}
    if not a.table_only:
        _prepare_to_run(out, a.domain_id)
        if not _run_missing(table, a, opts.render_size, failures):
            return 1
    text = table.write(failures)
    print('\n' + text)
    return 1 if failures else 0


if __name__ == '__main__':
    sys.exit(main())
