"""The stream table's table: one row per sequence and pose source from the cached runs (table_rows; the noise
seeds' mean rows), its markdown (markdown, LEGEND, run_details) and the files written from it
(write_table: ``OUT/stream_table.md`` and ``OUT/stream_table.json``, ``stream_table_<params>.*`` with parameters).
"""
from __future__ import annotations

import json
import math
import pathlib
from typing import Any, Dict, List, Tuple

import numpy as np

from dpv_sensor.benchmarks.stream_table_inputs import params_tag, run_key
from dpv_sensor.benchmarks.stream_table_runs import get_path

COLUMNS = [   # (header, run key, format)
    ('kf', 'keyframes_scored', '{:d}'),
    ('abs_rel', 'abs_rel', '{:.3f}'),
    ('d1', 'delta1', '{:.3f}'),
    ('ms abs_rel', 'ms_abs_rel', '{:.3f}'),
    ('scale q25', ('image_scale', 'q25'), '{:.3f}'),
    ('scale q75', ('image_scale', 'q75'), '{:.3f}'),
    ('scaled abs_rel', ('image_scale', 'scaled_abs_rel'), '{:.3f}'),
    ('anchors/kf', 'anchors_per_keyframe', '{:.0f}'),
    ('mount°', ('mount_check', 'angle_deg'), '{:.2f}'),
    ('mount σ°', ('mount_check', 'sigma_deg'), '{:.2f}'),
    ('offset ms', ('mount_check', 'offset_ms'), '{:+.1f}'),
    ('offset σ', ('mount_check', 'sigma_ms'), '{:.1f}'),
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


def _f(v):
    return v if isinstance(v, (int, float)) and not (isinstance(v, float) and not math.isfinite(v)) else None


def _value(run: Dict[str, Any], key):
    return _f(get_path(run, *key) if isinstance(key, tuple) else run.get(key))


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
                     f"{get_path(r, 'node', 'dropped_total')} | {(t.get('total_s') or 0) / 60:.1f} ({mins}) | "
                     f"{reasons} |")
    return '\n'.join(lines)


def write_table(out: pathlib.Path, runs, sequences, noise_seeds, params, command: str,
                failures: Dict[str, str], single_sources: Tuple[str, ...] = ('gt',),
                covariance: bool = False, twist: bool = False) -> Tuple[str, Dict[str, Any]]:
    rows = table_rows(runs, sequences, noise_seeds, params, single_sources)
    md = markdown(rows)
    done = len(runs)
    wanted = len(sequences) * (len(single_sources) + len(noise_seeds) * (1 + int(covariance) + int(twist)))
    times = [r['timing']['total_s'] for r in runs if get_path(r, 'timing', 'total_s') is not None]
    head = (f'Command: `{command}`\n\nParameters: {params_tag(params)}; {done} of {wanted} runs done'
            + (f', {len(failures)} failed' if failures else '')
            + (f'; {sum(times) / 60:.0f} min of runs (median {np.median(times) / 60:.1f} min per run)' if times
               else '') + '.')
    text = head + '\n\n' + md + '\n\n' + LEGEND + '\n\n' + run_details(runs) + '\n'
    if failures:
        text += '\nFailed runs:\n' + ''.join(f'- {k}: {v}\n' for k, v in failures.items())
    (out / f'{table_stem(params)}.md').write_text(text)
    data = {'command': command, 'params': params, 'sequences': sequences, 'noise_seeds': noise_seeds,
            'rows': rows, 'runs': {r['key']: r for r in runs}, 'failures': failures}
    from dpv_sensor.evaluation.offline import to_jsonable
    with open(out / f'{table_stem(params)}.json', 'w') as fh:
        json.dump(to_jsonable(data), fh, indent=1)
    return text, data


def table_stem(params: Dict[str, Any]) -> str:
    """The table files' name without extension: ``stream_table``, ``stream_table_<params>`` with parameters (offline
    runs carry ``offline=True`` among them)."""
    return 'stream_table' + ('' if not params else '_' + params_tag(params))
