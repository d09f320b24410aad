"""What an evaluation writes and prints: ``frames.csv`` (one row per keyframe), ``summary.json``, the montage,
sparsification and reliability plots (:func:`write_report`), and the comparison table of configurations
(:func:`table_row`, :func:`markdown_table`).
"""
from __future__ import annotations

import csv
import json
import math
import pathlib
from typing import Any, Dict, List, Optional, Sequence as SequenceT

import numpy as np

from dpv_sensor.common import to_jsonable
from dpv_sensor.evaluation import metrics as M
from dpv_sensor.evaluation.runner import KeyframeRecord

__all__ = ['write_frames_csv', 'write_report', 'table_row', 'markdown_table', 'get_path']

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


def get_path(d, path):
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
        v = get_path(summary, path)
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

