"""How accurate the metric anchors are, and what each way of holding the depth to them does (docs/anchors.md).

    python -m dpv_sensor.studies.anchors --data DATA --poses gt,noisy0cov
    python -m dpv_sensor.studies.anchors --data DATA --sequences icl_nuim_lr_kt3 --set bias_sigma_log=0.05 \
        --set "bias_sigma_log=0.02 max_tracks=1000"
    python -m dpv_sensor.studies.anchors --data DATA --sequences sun3d_3dmatch_frag2 --poses gt --no-veto \
        --mount 0 0 0 -0.0482 -0.0036 -0.0057 0.9988

Each (sequence, pose source) runs once through the node's pipeline (``evaluation.runner.run_sequence``, the
defaults with ``depth_anchors: off``) while every keyframe's refinement window is kept: its matches, refined poses,
match images and the flow's direction ratio (the veto), in memory (a run of 300 frames takes one to three
minutes). Then, for the anchor settings given with ``--set``
(:class:`~dpv_sensor.core.anchors.AnchorConfig` fields), each keyframe's anchors are triangulated again
(:func:`~dpv_sensor.stream.metric_anchors.reference_anchors`) and the published depth is held to them post hoc with
each mode (``off``, ``scale``, ``dense``: :class:`~dpv_sensor.stream.metric_anchors.AnchorAligner` on the depth at
its output size), which is what the node does to that keyframe's depth (the anchors do not feed back into the
filter). Printed per run: anchors per checked keyframe (median), the anchors' accuracy (per keyframe the median of
anchor depth / true depth at their pixels; the median and interquartile range of that over the keyframes), and per
mode abs_rel, the per-image scale's quartiles and the per-image-scaled abs_rel
(:func:`~dpv_sensor.evaluation.metrics.image_scale_summary`), ECE and δ<1.25 of the pixels with depth.

``--mount`` gives the odometry a camera mount (``T_base_camera``'s form: the poses are right-multiplied by it, as the
node does), e.g. the one ``calibrate_mount`` reads from the images; ``--no-veto`` triangulates the keyframes whose
window the veto would leave without anchors too, to see what those anchors would have said.
"""
from __future__ import annotations

import argparse
import pathlib
import sys
from typing import Dict, List

import numpy as np

__all__ = ['collect_windows', 'score_windows', 'main']

MODES = ('off', 'scale', 'dense')


class _Window:
    """What ``reference_anchors`` reads of a refinement result."""

    def __init__(self, matches, T_world_cam, match_images):
        self.matches, self.T_world_cam, self.match_images = matches, T_world_cam, match_images


def collect_windows(seq_dir: pathlib.Path, pose_source: str, mount_44=None) -> List[Dict]:
    """Run the sequence once and keep each published keyframe's depth, confidence, GT and refinement window;
    ``mount_44``: the camera mount the odometry's poses are right-multiplied by (None: the identity)."""
    from dpv_sensor.benchmarks.stream_table_inputs import odometry_poses, odometry_variance
    from dpv_sensor.data.sequence import Sequence
    from dpv_sensor.evaluation import offline as E, runner as RN
    from dpv_sensor.stream import estimator as EST
    windows = {}
    hold = EST.Estimator._hold_to_anchors

    def keep(self, ref, depth, conf, fallback=None):
        res = self._refinement_result()
        if res is not None and float(ref.stamp) in res.T_world_cam:
            windows[float(ref.stamp)] = (res.matches, {k: v.copy() for k, v in res.T_world_cam.items()},
                                         dict(res.match_images), getattr(self.pose_refiner, 'direction_ratio', None))
        return hold(self, ref, depth, conf, fallback)

    EST.Estimator._hold_to_anchors = keep
    try:
        seq = Sequence(seq_dir)
        config, _ = RN.build_config({'depth_anchors': 'off'})
        poses = odometry_poses(seq, pose_source)
        if mount_44 is not None:
            poses = [P @ mount_44 for P in poses]
        records, status = RN.run_sequence(seq, config, E.EvalOptions(progress=True), keep_images=False,
                                          poses=poses,
                                          pose_variance=odometry_variance(seq, pose_source))
    finally:
        EST.Estimator._hold_to_anchors = hold
    rows = []
    for rec in records:
        w = windows.get(rec.stamp)
        rows.append({'stamp': rec.stamp, 'depth': rec.depth_hw, 'conf': rec.confidence_hw, 'K': rec.K_33,
                     'gt': rec.gt_depth_hw, 'window': None if w is None else w[:3],
                     'direction_ratio': None if w is None else w[3], 'depth_range': status.depth_range})
    return rows


def score_windows(rows: List[Dict], config, veto: bool = True) -> Dict:
    """The anchors' accuracy and each mode's depth figures over the kept keyframes (module doc); ``veto`` False:
    the keyframes the veto leaves without anchors get theirs too."""
    from dpv_sensor.core import anchors as AM
    from dpv_sensor.evaluation.metrics import calibration_summary, image_scale_summary, within_ratio
    from dpv_sensor.stream import metric_anchors as MA
    per_mode = {m: {'pairs': [], 'abs_rel': [], 'conf': [], 'hit': []} for m in MODES}
    counts, accuracy = [], []
    for r in rows:
        anchors, ratio = None, r['direction_ratio']
        if r['window'] is not None and not (veto and ratio is not None and ratio[0] > ratio[1]):
            anchors = MA.reference_anchors(_Window(*r['window']), r['stamp'], config)
            counts.append(len(anchors))
            gt = r['gt']
            if len(anchors):
                x = np.c_[anchors.uv_n2, np.ones(len(anchors))] @ np.linalg.inv(anchors.K_33).T @ r['K'].T
                g = AM.sample_depth(np.where(gt > 0, gt, np.nan), x[:, :2])
                ok = np.isfinite(g)
                if ok.sum() >= 5:
                    accuracy.append(float(np.median(anchors.depth_n[ok] / g[ok])))
        for m in MODES:
            d, c, _rep = MA.AnchorAligner(m, config, depth_range=tuple(r['depth_range'])).apply(
                r['depth'], r['conf'], r['K'], anchors)
            v = (r['gt'] > 0) & np.isfinite(d) & (d > 0)
            if v.sum() < 100:
                continue
            q = per_mode[m]
            q['pairs'].append((d, r['gt']))
            q['abs_rel'].append(float(np.mean(np.abs(d[v] - r['gt'][v]) / r['gt'][v])))
            q['conf'].append(c[v])
            q['hit'].append(within_ratio(d[v], r['gt'][v]))
    out = {'keyframes': len(rows), 'anchors_per_keyframe': float(np.median(counts)) if counts else 0.0,
           'anchor_accuracy_median': float(np.median(accuracy)) if accuracy else None,
           'anchor_accuracy_iqr': float(np.subtract(*np.percentile(accuracy, [75, 25]))) if accuracy else None,
           'modes': {}}
    for m, q in per_mode.items():
        if not q['abs_rel']:
            continue
        cal = calibration_summary(np.concatenate(q['conf']), np.concatenate(q['hit']))
        out['modes'][m] = {'abs_rel': float(np.mean(q['abs_rel'])), 'image_scale': image_scale_summary(q['pairs']),
                           'ece': cal['ece'], 'delta1': cal['hit_rate']}
    return out


def _print(name: str, s: Dict) -> None:
    acc = s['anchor_accuracy_median']
    print(f"{name}: {s['keyframes']} keyframes, anchors per checked keyframe {s['anchors_per_keyframe']:.0f}, "
          + (f"anchor / true depth {acc:.3f} (IQR over keyframes {s['anchor_accuracy_iqr']:.3f})" if acc else
             'no anchors'))
    for m, f in s['modes'].items():
        sc = f['image_scale']
        print(f"  {m:6s} abs_rel {f['abs_rel']:.4f}  scale {sc['q25']:.3f}-{sc['q75']:.3f} (IQR {sc['iqr']:.3f})  "
              f"scaled abs_rel {sc['scaled_abs_rel']:.4f}  ECE {f['ece']:.3f}  d1 {f['delta1']:.3f}")


def main(argv=None) -> int:
    from dpv_sensor.core.anchors import AnchorConfig
    from dpv_sensor.stream.pose_buffer import pose7_to_matrix
    p = argparse.ArgumentParser(prog='python -m dpv_sensor.studies.anchors', description=__doc__.split('\n\n')[0])
    p.add_argument('--data', required=True, type=pathlib.Path, help='folder of sequence folders')
    p.add_argument('--sequences', nargs='*', help='sequence folder names (default: every one in DATA)')
    p.add_argument('--poses', default='gt,noisy0cov', help="comma list of pose sources (the stream table's)")
    p.add_argument('--set', action='append', default=[], metavar='"KEY=VALUE ..."',
                   help='AnchorConfig fields; repeat to score several settings on the same runs')
    p.add_argument('--mount', nargs=7, type=float, metavar=('X', 'Y', 'Z', 'QX', 'QY', 'QZ', 'QW'),
                   help="the odometry's camera mount (T_base_camera's form; default: the identity)")
    p.add_argument('--no-veto', action='store_true',
                   help='triangulate the keyframes the veto leaves without anchors too')
    args = p.parse_args(argv)
    try:
        configs = [AnchorConfig(**{k: type(getattr(AnchorConfig, k))(v) for k, v in
                                   (item.split('=', 1) for item in one.split())}) for one in args.set] or \
            [AnchorConfig()]
    except (ValueError, AttributeError, TypeError) as e:
        print(f'anchors: bad --set: {e}', file=sys.stderr)
        return 2
    names = args.sequences or sorted(d.name for d in args.data.iterdir() if (d / 'poses.txt').exists())
    for name in names:
        for src in args.poses.split(','):
            rows = collect_windows(args.data / name, src, None if args.mount is None else pose7_to_matrix(args.mount))
            for i, config in enumerate(configs):
                _print(f'{name} {src}' + (f' (--set {args.set[i]})' if len(configs) > 1 else ''),
                       score_windows(rows, config, veto=not args.no_veto))
    return 0


if __name__ == '__main__':
    sys.exit(main())
