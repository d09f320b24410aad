"""What the anchors' judge and the classical fallback do to a planted gross error (docs/anchors.md).

    python -m dpv_sensor.studies.anchor_overrule --data DATA --poses gt,noisy0cov

On a real desk the networks put the nearest pixels at about twice their depth; the development data has no such
failure, so it is planted: each (sequence, pose source) runs once through the node's pipeline at its defaults
(``evaluation.runner.run_sequence``), and at every keyframe, just before the anchors, the networks' depth of the
nearest quarter of the pixels (by the true depth) is doubled. The same keyframe is then held to its anchors three
ways, each from the same inputs (the anchors do not feed back into the filter): the networks' own depth (no plant:
what the defaults do to a right depth), the planted depth with ``anchor_fallback: off`` (the default: the judge
alone) and with ``classical``. Printed per run, over the keyframes: abs_rel of the planted pixels (the networks
before the plant; planted; judged; judged with the sweep), how many of them are published with confidence >= 0.9
and how many of those are within x1.25; abs_rel of the whole image (the networks; the defaults on them; planted;
judged; with the sweep); keyframes overruled of those checked; the anchors that fall on the planted pixels.
"""
from __future__ import annotations

import argparse
import pathlib
import sys
from typing import Dict, List

import numpy as np

__all__ = ['planted_run', 'summarise', 'main']

NEAR_QUANTILE = 25.0      # the nearest quarter of the valid pixels
PLANT_FACTOR = 2.0


def planted_run(seq_dir: pathlib.Path, pose_source: str) -> List[Dict]:
    """One run with the plant; per keyframe the true depth, the planted mask and the four depth/confidence pairs
    (processing size) with the judge's reports."""
    import torch
    from dpv_sensor.benchmarks.stream_table_inputs import odometry_poses, odometry_variance
    from dpv_sensor.data.sequence import Sequence
    from dpv_sensor.evaluation import offline as E, runner as RN
    from dpv_sensor.stream import estimator as EST
    seq = Sequence(seq_dir)
    index = {float(seq.stamp(i)): i for i in range(len(seq))}
    hold = EST.Estimator._hold_to_anchors
    rows: List[Dict] = []

    def planted(self, ref, depth, conf, fallback=None):
        i = index.get(float(ref.stamp))
        if i is None:
            return hold(self, ref, depth, conf, fallback)
        gt = RN.resize_nearest(np.asarray(seq.depth(i), np.float32), tuple(depth.shape[-2:]))
        net_d = depth[0].detach().float().cpu().numpy()
        net_c = conf[0].detach().float().cpu().numpy()
        valid = (gt > 0) & np.isfinite(net_d) & (net_d > 0)
        if valid.sum() < 100:
            return hold(self, ref, depth, conf, fallback)
        near = valid & (gt <= np.percentile(gt[valid], NEAR_QUANTILE))
        pd = net_d.copy()
        pd[near] *= PLANT_FACTOR
        pd_t = torch.as_tensor(pd, dtype=depth.dtype, device=depth.device)[None]
        row = {'gt': gt, 'valid': valid, 'near': near, 'net': (net_d, net_c), 'planted': (pd, net_c),
               'near_anchors': _anchors_in(self, ref, near)}
        d, c, _ = hold(self, ref, depth, conf, None)
        row['defaults'] = (d[0].float().cpu().numpy(), c[0].float().cpu().numpy())
        d, c, rep = hold(self, ref, pd_t, conf, None)
        row['judged'] = (d[0].float().cpu().numpy(), c[0].float().cpu().numpy())
        row['judged_report'] = rep
        out = hold(self, ref, pd_t, conf, fallback)
        row['sweep'] = (out[0][0].float().cpu().numpy(), out[1][0].float().cpu().numpy())
        row['sweep_report'] = out[2]
        rows.append(row)
        return out

    EST.Estimator._hold_to_anchors = planted
    try:
        # the sweep is built (anchor_fallback: classical) and handed only to the '+ sweep' variant; the others are
        # the defaults (anchor_fallback: off)
        config, _ = RN.build_config({'anchor_fallback': 'classical'})
        RN.run_sequence(seq, config, E.EvalOptions(progress=True), keep_images=False,
                        poses=odometry_poses(seq, pose_source), pose_variance=odometry_variance(seq, pose_source))
    finally:
        EST.Estimator._hold_to_anchors = hold
    return rows


def _anchors_in(estimator, ref, mask_hw: np.ndarray) -> int:
    """How many of the keyframe's anchors lie in ``mask_hw`` (processing size)."""
    from dpv_sensor.stream import metric_anchors as MA
    result = estimator._refinement_result()
    if result is None or float(ref.stamp) not in getattr(result, 'T_world_cam', {}):
        return 0
    a = MA.reference_anchors(result, float(ref.stamp), estimator.anchors.config)
    if not len(a):
        return 0
    K = ref.K_b33[0].double().cpu().numpy()
    uv = (np.c_[a.uv_n2, np.ones(len(a))] @ np.linalg.inv(a.K_33).T @ K.T)[:, :2]
    H, W = mask_hw.shape
    ix = np.clip(np.rint(uv[:, 0]), 0, W - 1).astype(np.int64)
    iy = np.clip(np.rint(uv[:, 1]), 0, H - 1).astype(np.int64)
    return int(mask_hw[iy, ix].sum())


def _abs_rel(d: np.ndarray, gt: np.ndarray, m: np.ndarray) -> float:
    m = m & np.isfinite(d) & (d > 0)
    return float(np.mean(np.abs(d[m] - gt[m]) / gt[m])) if m.any() else float('nan')


def summarise(rows: List[Dict]) -> Dict:
    """Means over the keyframes of the figures the module doc lists."""
    keys = ('net', 'defaults', 'planted', 'judged', 'sweep')
    near = {k: [] for k in keys}
    whole = {k: [] for k in keys}
    confident = {k: [0, 0, 0] for k in ('planted', 'judged', 'sweep')}     # near pixels, >= 0.9, of them right
    checked = overruled = 0
    for r in rows:
        gt, valid, m = r['gt'], r['valid'], r['near']
        for k in keys:
            d, c = r[k]
            near[k].append(_abs_rel(d, gt, m))
            whole[k].append(_abs_rel(d, gt, valid))
            if k in confident:
                hi = m & (c >= 0.9) & np.isfinite(d)
                confident[k][0] += int(m.sum())
                confident[k][1] += int(hi.sum())
                with np.errstate(divide='ignore', invalid='ignore'):
                    right = hi & (np.maximum(d / gt, gt / d) < 1.25)
                confident[k][2] += int(right.sum())
        rep = r['judged_report']
        if rep is not None and rep.applied != 'none':
            checked += 1
            overruled += int(rep.overruled_pixels > 0)
        elif rep is not None and rep.anchors:
            checked += 1
    return {'keyframes': len(rows), 'checked': checked, 'overruled': overruled,
            'near_anchors': float(np.median([r['near_anchors'] for r in rows])) if rows else 0.0,
            'near': {k: float(np.nanmean(v)) if v else None for k, v in near.items()},
            'whole': {k: float(np.nanmean(v)) if v else None for k, v in whole.items()},
            'confident': {k: (v[1] / v[0] if v[0] else 0.0, v[2] / v[1] if v[1] else None)
                          for k, v in confident.items()}}


def _row(name: str, s: Dict) -> str:
    n, w, c = s['near'], s['whole'], s['confident']

    def conf(k):
        share, right = c[k]
        return f'{100 * share:.0f} %' + (f' ({right:.2f})' if right is not None else '')
    return (f"| {name} | {n['net']:.3f} / {n['planted']:.3f} / {n['judged']:.3f} / {n['sweep']:.3f} | "
            f"{conf('planted')} / {conf('judged')} / {conf('sweep')} | "
            f"{w['net']:.4f} / {w['defaults']:.4f} / {w['planted']:.4f} / {w['judged']:.4f} / {w['sweep']:.4f} | "
            f"{s['overruled']} / {s['checked']} / {s['keyframes']} | {s['near_anchors']:.0f} |")


HEADER = ('| sequence, poses | planted pixels abs_rel: networks / planted / judged / + sweep | planted pixels at '
          'conf >= 0.9 (within x1.25): planted / judged / + sweep | whole image abs_rel: networks / defaults / '
          'planted / judged / + sweep | keyframes overruled / checked / all | anchors on the planted pixels, median '
          'per keyframe |\n|---|---|---|---|---|---|')


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog='python -m dpv_sensor.studies.anchor_overrule',
                                description=__doc__.split('\n\n')[0])
    p.add_argument('--data', required=True, type=pathlib.Path, help='folder of sequence folders')
    p.add_argument('--sequences', nargs='*', help='sequence folder names (default: every one in DATA)')
    p.add_argument('--poses', default='gt,noisy0cov', help="comma list of pose sources (the stream table's)")
    args = p.parse_args(argv)
    names = args.sequences or sorted(d.name for d in args.data.iterdir() if (d / 'poses.txt').exists())
    lines = [HEADER]
    for name in names:
        for src in args.poses.split(','):
            line = _row(f'{name}, {src}', summarise(planted_run(args.data / name, src)))
            print(line, flush=True)
            lines.append(line)
    print('\n'.join(lines))
    return 0


if __name__ == '__main__':
    sys.exit(main())
