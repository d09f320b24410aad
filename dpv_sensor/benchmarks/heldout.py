"""Held-out evaluation of the trained lite network vs the classical model vs a constant depth.

Runs dpv_sensor.evaluation.runner.run_sequence (the product's streaming path: keyframe selection, causal
5-keyframe windows, filter, 320x256 processing, output at the input size) with GT poses on the given
sequences (or, with ``--pose-noise``, odometry-like poses; the networks on those poses: no refinement window),
for filter modes none / global / knet, and
scores keyframe outputs with
dpv_sensor.evaluation.metrics (metric, frame means). Constant depth = the median GT depth of the sequence (an
oracle constant, i.e. a strong constant baseline), scored on the same keyframes.

    .venv/bin/python -m dpv_sensor.benchmarks.heldout --weights dpv_sensor/weights/lite.safetensors \
        --out results.json --data DATA [--seqs sun3d_3dmatch_frag1 sun3d_3dmatch_frag2] [--synthetic-seeds 0-9] \
        [--readout auto|relative|median|mean] [--pose-noise 0.01 0.15]
"""
import argparse
import pathlib
import json
import sys
import time

import numpy as np
import torch

from dpv_sensor.data.sequence import Sequence
from dpv_sensor.cli import add_setting
from dpv_sensor.stream.estimator import EstimatorConfig
from dpv_sensor.evaluation.metrics import MetricAccumulator
from dpv_sensor.evaluation.runner import EvalOptions, depth_limits, run_sequence
from dpv_sensor.evaluation.scoring import score_records
from dpv_sensor import params as P

def load_model(path):
    from safetensors.torch import load_file
    from dpv_sensor.core.nets.model import DPVNet
    try:
        from dpv_sensor.core.nets.checkpoint import load_checkpoint
        model, meta = load_checkpoint(path)
        return model.eval(), meta
    except Exception as e:          # plain safetensors (run dir's best_model.safetensors)
        print(f'load_checkpoint failed ({e}); reading plain safetensors', file=sys.stderr)
        m = DPVNet('lite')
        m.load_state_dict(load_file(path))
        return m.eval(), {}


def evaluate(seq, cfg, options: EvalOptions, model=None):
    """Keyframe rows and the summary of the sequence through the offline runner, scored in the estimator's range."""
    records, status = run_sequence(seq, cfg, options, model=model, keep_images=False)
    lo, hi = depth_limits(options, status)
    acc = score_records(records, min_depth=lo, max_depth=hi, occlusion_tol=options.occlusion_tol)
    return {'rows': acc.rows, 'summary': acc.summary()}


def summarize(res):
    s = res['summary']
    fm = s['metric']['frame_mean']
    out = {k: fm[k] for k in ('abs_rel', 'sq_rel', 'rmse', 'delta1')}
    out['ms_abs_rel'] = s['median_scaled']['frame_mean']['abs_rel']
    out['coverage'] = s['coverage']['frame_mean']
    c = s.get('confidence', {})
    out['confident_half_ratio'] = c.get('confident_half_ratio_frame_mean')
    out['confident_half_ratio_pooled'] = c.get('confident_half_ratio_pooled')
    out['ause'] = c.get('ause_frame_mean')
    out['frames'] = s['num_frames']
    ts = [r.get('time_ms') for r in res['rows'] if r.get('time_ms') is not None]
    out['time_ms'] = float(np.nanmean(ts)) if ts else None
    return out


def constant_baseline(seq, indices, d_min, d_max):
    deps = [seq.depth(i) for i in range(len(seq))]
    allv = np.concatenate([d[(d > 0) & np.isfinite(d)] for d in deps])
    c = float(np.median(allv))
    acc = MetricAccumulator(min_depth=d_min, max_depth=d_max)
    for i in indices:
        gt = deps[i]
        acc.add(np.full_like(gt, c), gt)
    s = acc.summary()
    fm = s['metric']['frame_mean']
    return {'abs_rel': fm['abs_rel'], 'sq_rel': fm['sq_rel'], 'rmse': fm['rmse'], 'delta1': fm['delta1'],
            'constant_m': c, 'frames': s['num_frames']}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument('--weights', required=True)
    ap.add_argument('--out', required=True)
    ap.add_argument('--data', type=pathlib.Path, default=None,
                    help='the folder that holds the --seqs sequence folders (needed unless --seqs is empty)')
    ap.add_argument('--seqs', nargs='*', default=['sun3d_3dmatch_frag1', 'sun3d_3dmatch_frag2'])
    ap.add_argument('--synthetic-seeds', default='', help="e.g. '0-9' (held-out synthetic seeds)")
    ap.add_argument('--synthetic-frames', type=int, default=60)
    ap.add_argument('--modes', nargs='*', default=[m for m in P.choices('filter_mode') if m != 'bayes'],
                    choices=P.choices('filter_mode'))
    add_setting(ap, 'window_mode')
    add_setting(ap, 'depth_readout', '--readout', dest='readout')
    add_setting(ap, 'confidence')
    ap.add_argument('--no-classical', action='store_true')
    ap.add_argument('--pose-noise', type=float, nargs=2, default=None, metavar=('REL_T', 'ROT_DEG'),
                    help='feed odometry-like poses instead of GT: per frame a translation error of REL_T of the '
                         'step and a rotation error of ROT_DEG, accumulating (data.trajectory.corrupt_trajectory, '
                         'seeded per sequence); depth is still scored against GT')
    ap.add_argument('--threads', type=int, default=2)
    a = ap.parse_args()
    if a.seqs and a.data is None:
        ap.error('--data is needed for --seqs (the folder that holds them); --seqs with no names for none')
    torch.set_num_threads(a.threads)
    model, meta = load_model(a.weights)
    D = model.preset.num_planes
    seqs = [(n, Sequence(str(a.data / n))) for n in a.seqs]
    if a.synthetic_seeds:
        from dpv_sensor.data.synthetic import render_sequence
        from dpv_sensor.training.dataset import check_heldout_seeds, parse_seeds
        try:
            seeds = check_heldout_seeds(parse_seeds(a.synthetic_seeds))
        except ValueError as e:
            ap.error(str(e))
        for s in seeds:
            seqs.append((f'synthetic_seed{s}',
                         render_sequence(s, a.synthetic_frames, width=320, height=240, lazy=True)))
    results = {'weights': a.weights, 'steps': meta.get('steps'), 'window_mode': a.window_mode, 'readout': a.readout,
               'confidence': a.confidence, 'pose_noise': a.pose_noise, 'sequences': {}}
    for k, (name, seq) in enumerate(seqs):
        r = {}
        kf_idx = None
        # odometry-like poses (data.trajectory.corrupt_trajectory, seeded per sequence) or GT
        options = EvalOptions(progress=False, consumer_odometry=False)
        if a.pose_noise is not None:
            options = EvalOptions(progress=False, consumer_odometry=False, pose_source='noisy',
                                  pose_noise=tuple(a.pose_noise), seed=k)
        for mode in a.modes:
            t0 = time.time()
            cfg = EstimatorConfig(preset=model.preset.name, measurement='network', filter_mode=mode,
                                  num_planes=D, window_mode=a.window_mode, depth_readout=a.readout,
                                  confidence=a.confidence, pose_refinement='off')
            res = evaluate(seq, cfg, options, model=model)
            r[f'net_{mode}'] = summarize(res)
            kf_idx = [row['index'] for row in res['rows']]
            print(name, 'net', mode, json.dumps(r[f'net_{mode}']), f'{time.time() - t0:.0f}s', flush=True)
        if not a.no_classical:
            for mode in [m for m in a.modes if m != 'knet']:
                cfg = EstimatorConfig(measurement='classical', filter_mode=mode, window_mode=a.window_mode,
                                      depth_readout=a.readout, confidence=a.confidence, pose_refinement='off')
                res = evaluate(seq, cfg, options)
                r[f'classical_{mode}'] = summarize(res)
                print(name, 'classical', mode, json.dumps(r[f'classical_{mode}']), flush=True)
        r['constant_median'] = constant_baseline(seq, kf_idx, 0.3, 8.0)
        print(name, 'constant', json.dumps(r['constant_median']), flush=True)
        results['sequences'][name] = r
    with open(a.out, 'w') as f:
        json.dump(results, f, indent=1)
    print(markdown_table(results))


def markdown_table(results) -> str:
    """abs_rel / delta1 per model row and real sequence, and the mean abs_rel over the synthetic ones."""
    seqs = results['sequences']
    real = [n for n in seqs if not n.startswith('synthetic')]
    synth = [n for n in seqs if n.startswith('synthetic')]
    rows = []
    for r in seqs.values():
        rows += [k for k in r if k not in rows]
    head = ['model'] + real + ([f'synthetic mean abs_rel ({len(synth)} seqs)'] if synth else [])
    lines = ['| ' + ' | '.join(head) + ' |', '|' + '---|' * len(head)]
    for k in rows:
        cells = [k]
        for n in real:
            e = seqs[n].get(k)
            cells.append(f"{e['abs_rel']:.3f} / {e['delta1']:.2f}" if e else '')
        if synth:
            v = [seqs[n][k]['abs_rel'] for n in synth if k in seqs[n]]
            cells.append(f'{np.mean(v):.3f}' if v else '')
        lines.append('| ' + ' | '.join(cells) + ' |')
    return '\n'.join(lines)


if __name__ == '__main__':
    main()
