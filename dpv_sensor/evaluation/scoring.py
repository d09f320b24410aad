"""Scoring of keyframe records against the GT: depth metrics, coverage, confidence quality, temporal consistency
and the error of the poses used (:func:`score_records`), and the JSON summary (:func:`summarize`).

Temporal consistency between consecutive records (skipped across a filter reset) is always computed with the
**GT poses**, so that it measures the depth maps, not the pose source, and is restricted to pixels visible in
both frames according to the GT depth. The summary's headline numbers are **frame means** (every keyframe counts
the same); the pooled, pixel-weighted numbers are reported next to them.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any, Dict, Iterable, Optional, Sequence as SequenceT, Tuple

import numpy as np

from dpv_sensor.core.pose_math import relative_pose_error_np
from dpv_sensor.evaluation import metrics as M
from dpv_sensor.evaluation.runner import KeyframeRecord, status_json

if TYPE_CHECKING:
    from dpv_sensor.stream.estimator_config import EstimatorStatus

__all__ = ['score_records', 'pose_rpe', 'relative_pose_error', 'summarize']

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
