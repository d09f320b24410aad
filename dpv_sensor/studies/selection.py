"""Checkpoint selection: score weight files on whole held-out sequences streamed through the estimator.

The same figures as the trainer's ``--val-stream-seeds`` validation (:mod:`dpv_sensor.training.stream_validation`):
each rendered seed is pushed frame by frame through ``Estimator`` with the node's defaults, once with the GT poses
and once with odometry-like poses (``--pose-noise``, seeded per sequence), and scored with frame-mean abs_rel.
Use seeds that are never trained on and never reported (the README uses 20-25 for picking exports and 50-57
for reporting), and pick by the mean of the two columns.

    .venv/bin/python -m dpv_sensor.studies.selection --weights A.safetensors B.safetensors --seeds 20-25 \
        [--frames 60] [--pose-noise 0.03 0.5] [--modes knet] [--world-scale 1] [--threads 2] [--device cpu] \
        [--out selection.json]

Prints a table (weights, abs_rel with GT poses, with noisy poses, their mean, delta1, confident-half ratios) and,
with several weights, each one's paired difference from the first: the mean over seeds of its per-seed score minus
the first's (score = the mean of the GT and noisy abs_rel of that seed), with its standard error and how many seeds
it wins. A difference within about two standard errors is noise: six seeds rarely separate 0.004.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Dict, List, Optional

import numpy as np
import torch

from dpv_sensor.training.dataset import parse_seeds
from dpv_sensor.training.stream_validation import StreamValidationSpec, StreamValidator, stream_metric_key
from dpv_sensor import params as P
from dpv_sensor.cli import add_setting


def score_weights(paths: List[str], spec: StreamValidationSpec, progress=None,
                  device: str = P.default('device')) -> Dict[str, Dict]:
    """{path: {stream_[noisy_]net_<mode>: metrics, 'steps': steps in the metadata}} (sequences rendered once)."""
    from dpv_sensor.benchmarks.heldout import load_model
    validator = StreamValidator(spec)
    out: Dict[str, Dict] = {}
    for p in paths:
        try:
            model, meta = load_model(p)
        except Exception as e:
            raise ValueError(f'cannot load weights {p}: {type(e).__name__}: {e}') from None
        t0 = time.time()
        res = validator(model, device, progress=progress)
        res['steps'] = meta.get('steps')
        res['seconds'] = round(time.time() - t0, 1)
        out[p] = res
    return out


def markdown_table(results: Dict[str, Dict], modes) -> str:
    """One row per weights and mode: abs_rel with GT / noisy poses and their mean, delta1, confident-half."""
    lines = ['| weights | steps | mode | abs_rel GT poses | abs_rel noisy poses | mean | δ1 GT / noisy '
             '| conf½ GT / noisy |',
             '|---|---|---|---|---|---|---|---|']
    for p, r in results.items():
        for mode in modes:
            g, n = r.get(stream_metric_key(mode, False)), r.get(stream_metric_key(mode, True))
            if g is None:
                continue
            both = [g] + ([n] if n else [])

            def cell(k, digits):
                return ' / '.join(f'{e[k]:.{digits}f}' for e in both)

            mean = float(np.mean([e['abs_rel'] for e in both]))
            lines.append(f"| {p} | {r.get('steps')} | {mode} | {g['abs_rel']:.4f} | "
                         f"{n['abs_rel'] if n else float('nan'):.4f} | {mean:.4f} | {cell('delta1', 3)} | "
                         f"{cell('confident_half_ratio', 2)} |")
    return '\n'.join(lines)


def per_seed_scores(result: Dict, mode: str) -> np.ndarray:
    """Per-seed score of one weights file: abs_rel with GT poses, averaged with the noisy-pose one when present."""
    cols = [np.asarray(result[k]['per_seed'], np.float64) for k in (stream_metric_key(mode, False),
                                                                      stream_metric_key(mode, True)) if k in result]
    if not cols:
        raise KeyError(f'no per-seed scores for mode {mode!r}')
    return np.mean(cols, axis=0)


def paired_differences(results: Dict[str, Dict], mode: str = 'knet') -> List[Dict]:
    """For each weights file after the first: mean per-seed score difference to the first (negative = better),
    its standard error (NaN with one seed) and the number of seeds where it is lower."""
    names = list(results)
    if len(names) < 2:
        return []
    base = per_seed_scores(results[names[0]], mode)
    rows = []
    for name in names[1:]:
        d = np.round(per_seed_scores(results[name], mode) - base, 9)   # per-seed figures carry 4 decimals
        se = float(d.std(ddof=1) / np.sqrt(d.size)) if d.size > 1 else float('nan')
        rows.append({'weights': name, 'base': names[0], 'mean_diff': float(d.mean()) + 0.0, 'std_err': se,
                     'seeds_better': int((d < 0).sum()), 'seeds': int(d.size)})
    return rows


def difference_table(rows: List[Dict], mode: str) -> str:
    if not rows:
        return ''
    lines = [f'paired difference from {rows[0]["base"]} ({mode}, per-seed mean of GT and noisy abs_rel; '
             f'negative = better):', '', '| weights | difference | standard error | seeds better |',
             '|---|---|---|---|']
    for r in rows:
        lines.append(f"| {r['weights']} | {r['mean_diff']:+.4f} | {r['std_err']:.4f} | "
                     f"{r['seeds_better']} of {r['seeds']} |")
    return '\n'.join(lines)


def main(argv: Optional[List[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog='selection', description=__doc__.split('\n\n')[0])
    ap.add_argument('--weights', nargs='+', required=True, help="exported .safetensors (or a run dir's best_model)")
    ap.add_argument('--seeds', default='20-25', help='held-out rendered seeds (0..99), never reported')
    ap.add_argument('--frames', type=int, default=60, help='frames per sequence (320x240, 30 Hz)')
    ap.add_argument('--pose-noise', type=float, nargs=2, default=[0.03, 0.5], metavar=('REL_T', 'ROT_DEG'),
                    help='odometry-like pose errors per frame of the noisy pass (0 0: GT poses only)')
    ap.add_argument('--modes', nargs='+', default=[P.default('filter_mode')], choices=P.choices('filter_mode'),
                    help='filter modes')
    ap.add_argument('--world-scale', type=float, default=1.0,
                    help='see each sequence in a world this many times larger (depths and translations; the same '
                         'images): 0.5 puts every surface at half its distance, a check that depth is read from '
                         "the views' geometry rather than from the usual sizes of rooms")
    ap.add_argument('--threads', type=int, default=2)
    add_setting(ap, 'device', help='torch device of the estimator: cpu, cuda, cuda:N (the paper preset wants a GPU: '
                                   '2.5 s a keyframe in float32 on a 2-core CPU)')
    ap.add_argument('--out', default=None, help='write the results as JSON here')
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    try:
        spec = StreamValidationSpec(seeds=parse_seeds(a.seeds), frames=a.frames, pose_noise=tuple(a.pose_noise),
                                    modes=tuple(a.modes), world_scale=a.world_scale).check()
        res = score_weights(a.weights, spec, progress=lambda m: print(m, flush=True), device=a.device)
    except ValueError as e:        # bad seeds / modes, weights that do not load, a device that is missing
        print(f'selection: {e}', file=sys.stderr)
        return 2
    diffs = {mode: paired_differences(res, mode) for mode in spec.modes}
    if a.out:
        with open(a.out, 'w') as f:
            json.dump({'seeds': list(spec.seeds), 'frames': spec.frames, 'pose_noise': list(spec.pose_noise),
                       'world_scale': spec.world_scale,
                       'results': res, 'paired_differences': diffs}, f, indent=1)
    print(markdown_table(res, spec.modes))
    for mode, rows in diffs.items():
        if rows:
            print()
            print(difference_table(rows, mode))
    return 0


if __name__ == '__main__':
    sys.exit(main())
