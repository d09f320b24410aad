"""What each factor set of the refinement window would have done, window by window: the evidence a per-window
decision could use, and the relative-pose error each choice leaves.

    python -m dpv_sensor.studies.window_decisions --data DATA [--sequences ...] \
        [--poses noisy0cov noisy1cov noisy0 gt] [--frames 0] [--out out/window_decisions]

Each sequence runs through the node's pipeline in this process at the node's defaults with the pose source of the
stream table (``gt``, ``noisy<k>``, ``noisy<k>cov``): the default window refines the poses the depth is computed
with. At every window, shadow refiners that start from the default refiner's state (its poses, odometry and
keypoints; each keeps its own photometric alignments from window to window) solve the same window with other factor
sets (CANDIDATES). Per window and candidate, the error of each source's pose relative to the reference
(``T_src_ref``, what the plane sweep uses) against the sequence's ground truth: rotation (deg), translation (mm) and
both as the image shift they cause at the window's median depth (``shift_px = f (rot + trans / depth)``).
``off`` is the odometry's own relative pose (refinement off).

Per window the evidence (``features``): the baseline to the nearest source against the median depth, the turn to
it, the odometry step's std and where it came from, per keypoint pair the inliers, parallax, stated stds, residual
and the disagreement with the odometry (rotation in degrees and as a chi-square under both covariances; direction),
per photometric alignment its convergence, residual ratio and disagreement with the odometry and the keypoints.

Written: ``OUT/<sequence>__<poses>.jsonl`` (one line per window), ``OUT/window_decisions.md`` (per sequence and
pose source: the mean errors of every candidate and of the per-window best, the oracle a decision rule could reach
at most).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import pathlib
import sys
from typing import Any, Dict, List, Optional

import numpy as np

#: the factor sets solved beside the default (dataclass fields of PoseRefinerConfig set on top of the defaults)
CANDIDATES: Dict[str, Dict[str, Any]] = {
    'direction': {'keypoint_direction': 'keypoints'},
    'photometric': {'max_sources': 2},
    'both': {'keypoint_direction': 'keypoints', 'max_sources': 2},
}
#: the refiner's state a shadow starts each window from (the default refiner's, copied; '_factors' excluded: the
#: shadow keeps its own photometric alignments)
_STATE = ('_odom', '_est', '_pyramids', '_features', '_cov')


def _deg(rad: float) -> float:
    return math.degrees(rad)


def _rotvec_deg(R: np.ndarray) -> np.ndarray:
    import cv2
    return np.degrees(cv2.Rodrigues(np.asarray(R, np.float64))[0].ravel())


class Recorder:
    """The default refiner's ``refine`` wrapped: it refines as always, then the shadows solve the same window from
    the same state, and one row per window is kept. The recorder is the estimator's pose refiner (it hands every
    call to the default refiner): it asks for the predicted depth at the finest grid any of them reads
    (``predicted_depth_stride``; the photometric shadows align against every pixel), and each refiner gets every
    n-th pixel of it, as the node would give it at its own stride."""

    def __init__(self, main, candidates: Dict[str, Any], gt_pose):
        from dpv_sensor.stream.window_refiner import WindowPoseRefiner
        self.main = main
        self.shadows = {name: WindowPoseRefiner(cfg) for name, cfg in candidates.items()}
        self.gt_pose = gt_pose              # key -> T_world_cam of the ground truth
        self.rows: List[Dict[str, Any]] = []
        self.predicted_depth_stride = min([main.predicted_depth_stride] +
                                          [s.predicted_depth_stride for s in self.shadows.values()])
        self._refine = main.refine
        main.refine = self.refine

    def __call__(self, request):
        return self.main(request)

    def __getattr__(self, name):            # last_result, counters, reset, ...: the default refiner's
        return getattr(self.main, name)

    def _depth_for(self, refiner, depth_ref, conf_ref, K_depth_33, inv_depth_std_ref):
        """The depth arguments as the node hands them to ``refiner``: the pixels of its own stride."""
        k = refiner.predicted_depth_stride // self.predicted_depth_stride
        if k == 1 or depth_ref is None:
            return depth_ref, conf_ref, K_depth_33, inv_depth_std_ref
        from dpv_sensor.core.geometry import subsampled_intrinsics
        K = None if K_depth_33 is None else subsampled_intrinsics(K_depth_33, k)
        return (depth_ref[::k, ::k], None if conf_ref is None else conf_ref[::k, ::k], K,
                None if inv_depth_std_ref is None else inv_depth_std_ref[::k, ::k])

    def refine(self, ref, sources, depth_ref=None, conf_ref=None, K_depth_33=None, inv_depth_std_ref=None):
        before = {name: (dict(getattr(self.main, name))) for name in _STATE}
        depth_refs, anchor = self.main._depth_refs, self.main._anchor_key
        depth = (depth_ref, conf_ref, K_depth_33, inv_depth_std_ref)
        res = self._refine(ref, sources, *self._depth_for(self.main, *depth))
        if depth_ref is None or not sources or not res.tracking_ok:
            for s in self.shadows.values():
                s.reset()
            return res
        shadow_res = {}
        for name, sh in self.shadows.items():
            for field in _STATE:
                state = dict(before[field])
                if field in ('_pyramids', '_features'):
                    state.update(getattr(self.main, field))      # caches: pure functions of the images
                setattr(sh, field, state)
            sh._depth_refs, sh._anchor_key = depth_refs, anchor
            shadow_res[name] = sh.refine(ref, sources, *self._depth_for(sh, *depth))
        self.rows.append(self._row(ref, sources, depth_ref, res, shadow_res))
        return res

    def _row(self, ref, sources, depth_ref, res, shadow_res) -> Dict[str, Any]:
        from dpv_sensor.core.photometric import pose_error
        from dpv_sensor.stream.window_graph import relative_pose
        d = np.asarray(depth_ref.numpy() if hasattr(depth_ref, 'numpy') else depth_ref, np.float64)
        d = d[np.isfinite(d) & (d > 0)]
        depth_m = float(np.median(d)) if d.size else float('nan')
        gt_ref = self.gt_pose(ref.key)
        focal_px = float(ref.K_33[0, 0])
        results = {'default': res, **shadow_res}
        errors: Dict[str, Dict[str, List[float]]] = {k: {'rot_deg': [], 'trans_mm': [], 'shift_px': []}
                                                     for k in ['off', *results]}
        for i, s in enumerate(sources):
            T_gt = relative_pose(self.gt_pose(s.key), gt_ref)
            estimates = {'off': relative_pose(s.T_world_cam_odom_44, ref.T_world_cam_odom_44),
                         **{k: r.T_src_ref[i] for k, r in results.items()}}
            for k, T in estimates.items():
                dt, dr = pose_error(T_gt, T)
                errors[k]['rot_deg'].append(float(dr))
                errors[k]['trans_mm'].append(1e3 * float(dt))
                errors[k]['shift_px'].append(focal_px * (math.radians(dr) + dt / max(depth_m, 0.1)))
        return {'key': float(ref.key), 'sources': [float(s.key) for s in sources],
                'errors': {k: {m: float(np.mean(v)) for m, v in e.items()} for k, e in errors.items()},
                'gates': {k: r.gate for k, r in results.items()},
                'features': self._features(ref, sources, depth_m, res, shadow_res)}

    def _features(self, ref, sources, depth_m, res, shadow_res) -> Dict[str, Any]:
        from dpv_sensor.core.pose_math import rotation_angle_np
        from dpv_sensor.stream.window_graph import odometry_step_covariance, relative_pose
        from dpv_sensor.stream.window_refiner import _key_distance
        cfg = self.main.config
        order = sorted(range(len(sources)), key=lambda i: _key_distance(sources[i].key, ref.key))
        near = sources[order[0]]
        rel = relative_pose(near.T_world_cam_odom_44, ref.T_world_cam_odom_44)
        base = float(np.linalg.norm(rel[:3, 3]))
        f: Dict[str, Any] = {
            'depth_m': depth_m, 'baseline_m': base, 'parallax': base / max(depth_m, 1e-6),
            'turn_deg': _deg(rotation_angle_np(rel[:3, :3])), 'skipped': res.skipped is not None,
            'odom_rot_deg': _deg(res.odometry.rot_rad) if res.odometry else None,
            'odom_trans_mm': 1e3 * res.odometry.trans_m if res.odometry else None,
            'odom_source': res.odometry.source if res.odometry else None}
        pairs = []
        for i, kp in zip(order[:cfg.keypoint_sources], res.keypoints):
            s = sources[i]
            T0 = relative_pose(s.T_world_cam_odom_44, ref.T_world_cam_odom_44)      # T_src_ref, odometry
            p: Dict[str, Any] = {'ok': bool(kp.ok), 'inliers': int(kp.inliers), 'parallax_px': float(kp.parallax_px),
                                 'sigma_rot_deg': _deg(kp.sigma_rot_rad), 'sigma_dir_deg': _deg(kp.sigma_dir_rad),
                                 'residual_px': float(kp.residual_px)}
            if kp.ok:
                d_rot = _rotvec_deg(kp.R_b_a @ T0[:3, :3].T)
                p['rot_vs_odom_deg'] = float(np.linalg.norm(d_rot))
                a, b = (s, ref) if s.key <= ref.key else (ref, s)
                S = odometry_step_covariance(a.T_world_cam_odom_44, b.T_world_cam_odom_44, a.odometry_covariance(),
                                             b.odometry_covariance(), cfg)
                dr = np.radians(d_rot)
                p['rot_chi2'] = float(dr @ np.linalg.solve(S[:3, :3] + kp.rotation_covariance(), dr))
                if kp.t_dir_b is not None and np.linalg.norm(T0[:3, 3]) > 0:
                    u = T0[:3, 3] / np.linalg.norm(T0[:3, 3])
                    p['dir_vs_odom_deg'] = _deg(math.acos(float(np.clip(u @ kp.t_dir_b, -1, 1))))
            pairs.append(p)
        f['keypoints'] = pairs
        photo = []
        ph = shadow_res.get('photometric')
        for i in order[:2]:
            al = ph.alignments[i] if ph is not None and i < len(ph.alignments) else None
            if al is None:
                continue
            T0 = relative_pose(sources[i].T_world_cam_odom_44, ref.T_world_cam_odom_44)
            q = {'converged': bool(al.converged), 'residual_ratio': float(al.residual_ratio),
                 'valid': int(al.num_valid),
                 'rot_vs_odom_deg': float(np.linalg.norm(_rotvec_deg(al.T_src_ref_44[:3, :3] @ T0[:3, :3].T)))}
            kp = res.keypoints[order.index(i)] if order.index(i) < len(res.keypoints) else None
            if kp is not None and kp.ok:
                q['rot_vs_keypoints_deg'] = float(np.linalg.norm(_rotvec_deg(al.T_src_ref_44[:3, :3] @ kp.R_b_a.T)))
            photo.append(q)
        f['photometric'] = photo
        return f


def run(seq_dir: pathlib.Path, pose_source: str, frames: int, progress: bool) -> List[Dict[str, Any]]:
    """One sequence with one pose source through the pipeline at the node's defaults; the rows of its windows."""
    from dpv_sensor.benchmarks import stream_table_inputs as ST
    from dpv_sensor.data.sequence import Sequence
    from dpv_sensor.evaluation import runner as RN
    from dpv_sensor.stream.window_refiner import PoseRefinerConfig, WindowPoseRefiner
    seq = Sequence(seq_dir)
    n = len(seq) if frames <= 0 else min(frames, len(seq))
    config, _ = RN.build_config({})
    if config.pose_refinement != 'window':
        raise ValueError('the node default is no refinement window: nothing to decide')
    base = PoseRefinerConfig.from_params(config.as_dict())
    main = WindowPoseRefiner(base)
    stamps = np.asarray(seq.stamps, np.float64)
    gt = [np.asarray(seq.pose(i), np.float64) for i in range(len(seq))]

    def gt_pose(key):
        return gt[int(np.argmin(np.abs(stamps - float(key))))]
    options = RN.EvalOptions(max_frames=n, progress=progress)
    rec = Recorder(main, {k: dataclasses.replace(base, **v) for k, v in CANDIDATES.items()}, gt_pose)
    poses = ST.odometry_poses(seq, pose_source)[:n]
    var = ST.odometry_variance(seq, pose_source)
    RN.run_sequence(seq, config, options, keep_images=False, poses=poses,
                    pose_variance=None if var is None else var[:n], pose_refiner=rec)
    return rec.rows


def summary_rows(rows_by_run: Dict[str, List[Dict[str, Any]]]) -> List[Dict[str, Any]]:
    """Per run: windows, and per candidate (and the per-window best by shift) the mean rot / trans / shift."""
    out = []
    for name, rows in rows_by_run.items():
        if not rows:
            out.append({'run': name, 'windows': 0})
            continue
        cands = list(rows[0]['errors'])
        r: Dict[str, Any] = {'run': name, 'windows': len(rows)}
        for c in cands:
            r[c] = {m: float(np.mean([w['errors'][c][m] for w in rows])) for m in ('rot_deg', 'trans_mm', 'shift_px')}
        best = [min((k for k in cands if k != 'off'), key=lambda k: w['errors'][k]['shift_px']) for w in rows]
        r['best'] = {m: float(np.mean([w['errors'][b][m] for w, b in zip(rows, best)]))
                     for m in ('rot_deg', 'trans_mm', 'shift_px')}
        r['best_counts'] = {c: best.count(c) for c in cands if c != 'off'}
        out.append(r)
    return out


def markdown(summ: List[Dict[str, Any]]) -> str:
    cands = ['off', 'default', *CANDIDATES, 'best']
    head = '| run | windows | ' + ' | '.join(cands) + ' | best picks |'
    lines = ["Mean over windows of the sources' relative-pose error: rotation deg / translation mm / image shift px "
             '(f (rot + trans / median depth)). best = per window the candidate (not off) with the least shift: '
             'what a per-window decision could reach at most.', '', head, '|---' * (len(cands) + 3) + '|']
    for r in summ:
        if not r['windows']:
            lines.append(f"| {r['run']} | 0 |" + ' |' * (len(cands) + 1))
            continue
        cells = [f"{r[c]['rot_deg']:.3f} / {r[c]['trans_mm']:.1f} / {r[c]['shift_px']:.2f}" for c in cands]
        picks = ', '.join(f'{k} {v}' for k, v in r['best_counts'].items())
        lines.append(f"| {r['run']} | {r['windows']} | " + ' | '.join(cells) + f' | {picks} |')
    return '\n'.join(lines) + '\n'


def main(argv: Optional[List[str]] = None) -> int:
    from dpv_sensor.benchmarks.stream_table_inputs import add_folder_args, chosen_folders
    from dpv_sensor.cli import tool_argv
    argv = tool_argv(argv)
    p = argparse.ArgumentParser(prog='window_decisions', description=__doc__.split('\n\n')[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    add_folder_args(p)
    p.add_argument('--poses', nargs='*', default=['noisy0cov'], help='pose sources (stream table names)')
    p.add_argument('--frames', type=int, default=0, help='first frames of each sequence (0: all)')
    p.add_argument('--threads', type=int, default=2)
    p.add_argument('--out', type=pathlib.Path, default=pathlib.Path('out/window_decisions'))
    p.add_argument('--quiet', action='store_true')
    a = p.parse_args(argv)
    folders = chosen_folders(p, a)
    names = list(folders)
    import torch
    torch.set_num_threads(a.threads)
    a.out.mkdir(parents=True, exist_ok=True)
    rows_by_run = {}
    for n in names:
        for src in a.poses:
            path = a.out / f'{n}__{src}.jsonl'
            if path.is_file():
                rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
            else:
                rows = run(folders[n], src, a.frames, not a.quiet)
                path.write_text(''.join(json.dumps(r) + '\n' for r in rows))
            rows_by_run[f'{n} {src}'] = rows
            print(f'{n} {src}: {len(rows)} windows', flush=True)
    text = markdown(summary_rows(rows_by_run))
    (a.out / 'window_decisions.md').write_text(f'Command: `python -m dpv_sensor.studies.window_decisions '
                                               f'{" ".join(argv)}`\n\n' + text)
    print('\n' + text)
    return 0


if __name__ == '__main__':
    sys.exit(main())
