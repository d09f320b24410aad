"""One run of the stream table: a sequence with one pose source replayed through the node process and scored
(run_one), or through the node's pipeline in this process (run_one_offline, ``--offline``); each returns the run's
JSON dict, the content of a cached run (RUN_VERSION). The scoring helpers: the oracle constant depth on the same
pixels (oracle_constant, constant_on_same_pixels), the node's recorded /diagnostics (diagnostics_series,
keyframe_times_ms, reset_reasons) and get_path (a value nested in a summary or run dict).
"""
from __future__ import annotations

import math
import pathlib
import re
import shutil
import time
from typing import Any, Dict, List

import numpy as np

from dpv_sensor.benchmarks.stream_table_inputs import (PosedView, noise_description, odometry_poses,
                                                       odometry_twist_variance, odometry_variance, run_key)

RUN_VERSION = 3   # bump when a cached run's content changes meaning (2: calibration; 3: image scale, anchors)
# (the mount check's figures are new keys: runs without them show blanks, no bump)


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


def get_path(d, *path):
    """d[path[0]][path[1]]...; None where a key is missing or a value is not a dict."""
    for p in path:
        if not isinstance(d, dict) or p not in d:
            return None
        d = d[p]
    return d


# --------------------------------------------------------------------------------------------------------------
# one run
# --------------------------------------------------------------------------------------------------------------
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
        'image_scale': image_scale(records, min_depth, max_depth),
        'anchors_per_keyframe': D._as_number(d.get('anchors_per_keyframe')),
        'anchors_keyframes': d.get('anchors_keyframes'),
        'mount_check': mount_check_numbers(d),
        'coverage': summary['coverage']['frame_mean'],
        'confident_half_ratio': get_path(summary, 'confidence', 'confident_half_ratio_frame_mean'),
        'confident_half_ratio_pooled': get_path(summary, 'confidence', 'confident_half_ratio_pooled'),
        'ause': get_path(summary, 'confidence', 'ause_frame_mean'),
        'mean_confidence': get_path(summary, 'confidence', 'mean_confidence'),
        'calibration': summary.get('calibration'),
        'temporal': get_path(summary, 'temporal_consistency', 'pair_mean'),
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
    records, status = RN.run_sequence(seq, config, E.EvalOptions(progress=progress), keep_images=False,
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
        'image_scale': image_scale(records, min_depth, max_depth),
        'anchors_per_keyframe': anchors_per_keyframe(status),
        'coverage': summary['coverage']['frame_mean'],
        'confident_half_ratio': get_path(summary, 'confidence', 'confident_half_ratio_frame_mean'),
        'mean_confidence': get_path(summary, 'confidence', 'mean_confidence'),
        'calibration': summary.get('calibration'),
        'output_resets': len(resets), 'output_reset_reasons': resets,
        # what the window refiner used (factor decisions) and, with rotation evidence auto, the flow pairs' last
        # median direction ratio against its threshold
        'pose_refinement_factors': dict(getattr(status, 'pose_refinement_factors', None) or {}),
        'pose_refinement_direction_ratio': getattr(status, 'pose_refinement_direction_ratio', None),
        'keyframe_ms_median': float(np.median(times)) if times else None,
        'constant': constant_on_same_pixels(records, oracle_constant(seq, min_depth, max_depth), min_depth,
                                            max_depth),
        'min_depth': min_depth, 'max_depth': max_depth,
        'timing': {'total_s': round(time.perf_counter() - t_all, 1)}, 'finished': time.strftime('%Y-%m-%d %H:%M:%S'),
    })


def image_scale(records, min_depth=None, max_depth=None) -> Dict[str, Any]:
    """The per-image scale's quartiles and the per-image-scaled abs_rel of a run's records
    (evaluation.metrics.image_scale_summary)."""
    from dpv_sensor.evaluation.metrics import image_scale_summary
    return image_scale_summary(((r.depth_hw, r.gt_depth_hw) for r in records), min_depth, max_depth)


def mount_check_numbers(diag: Dict[str, str]) -> Dict[str, Any]:
    """The mount check's figures from /diagnostics' text (``ros.diagnostics.mount_values``): the angle and the
    largest axis sigma (deg), the rotation vector, the time offset and its sigma (ms); the texts as they were."""
    out: Dict[str, Any] = {'mount_estimate': diag.get('mount_estimate'),
                           'time_offset_estimate': diag.get('time_offset_estimate')}
    m = re.search(r'([\d.]+) deg, rotation vector \[([^\]]+)\] \+- \[([^\]]+)\]', diag.get('mount_estimate') or '')
    if m:
        sig = [float(v) for v in m.group(3).split(',') if v.strip() != 'n/a']
        out.update(angle_deg=float(m.group(1)), rotvec_deg=[float(v) for v in m.group(2).split(',')],
                   sigma_deg=max(sig) if sig else None)
    m = re.search(r'([+-][\d.]+) \+- ([\d.]+) ms', diag.get('time_offset_estimate') or '')
    if m:
        out.update(offset_ms=float(m.group(1)), sigma_ms=float(m.group(2)))
    return out


def anchors_per_keyframe(status) -> float:
    """Metric anchors per checked keyframe from an estimator status (0 when none was checked)."""
    a = getattr(status, 'anchors', None) or {}
    checked = a.get('keyframes_checked', 0)
    return float(a.get('anchors', 0)) / checked if checked else 0.0
