"""How the depth answers the plane sweep's pose errors: a chosen share of the odometry's error against what the
window refiner leaves in the closed loop.

    python -m dpv_sensor.studies.pose_error_depth --data DATA --sequences icl_nuim_lr_kt3 --poses noisy0 \
        [--scales 0 0.3 0.6 0.73:1 1:0] [--refiners default refine_photometric_sources=4] [--out DIR]

Each row runs one sequence through the node's pipeline in this process (the node's defaults otherwise) with the
odometry of a stream-table pose source (``noisy<k>``; ``noisy<k>cov`` publishes its covariance) and scores its
keyframe depth against the ground truth (frame-mean abs_rel):

- ``gt``: the dataset's poses, refinement off; ``odometry``: the noisy odometry, refinement off.
- ``scaled R:T``: refinement off, but each window's sources are handed to the plane sweep at the ground truth's pose
  relative to the reference times the odometry's error scaled by R (rotation, as a rotation vector) and T
  (translation) (:class:`ScaledErrorRefiner`, an oracle that exists only here); ``R`` alone scales both. The
  reference keeps its odometry pose, so the filter's propagation between keyframes sees the whole drift.
- each ``--refiners`` entry: the node's window refiner with those parameters on top of the defaults (``default``:
  none).

Every row also reports the rotation error of the sweep's relative poses ``T_src_ref`` against the ground truth (mean
over every source of every window, degrees), split into the part about the axis ``t x z`` (``t`` the baseline in
the source camera, ``z`` its optical axis: a turn about it shifts the image along the epipolar lines, as a depth
change does) and the rest, beside the same for the odometry's own relative poses in the same windows.

Written: ``OUT/pose_error_depth.json`` and ``.md`` (the table).
"""
from __future__ import annotations

import argparse
import json
import pathlib
import sys
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np

__all__ = ['ScaledErrorRefiner', 'ErrorLog', 'rotation_error_parts', 'scale_error', 'main']


def _rotvec(R_33: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation
    return Rotation.from_matrix(R_33).as_rotvec()


def _rotation(rotvec_3: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation
    return Rotation.from_rotvec(rotvec_3).as_matrix()


def scale_error(T_true_44: np.ndarray, T_est_44: np.ndarray, rot_scale: float, trans_scale: float) -> np.ndarray:
    """``T_true`` times the error ``T_true^-1 T_est`` with its rotation vector scaled by ``rot_scale`` and its
    translation by ``trans_scale`` (0, 0: ``T_true``; 1, 1: ``T_est``)."""
    D = np.linalg.inv(T_true_44) @ T_est_44
    Ds = np.eye(4)
    Ds[:3, :3] = _rotation(rot_scale * _rotvec(D[:3, :3]))
    Ds[:3, 3] = trans_scale * D[:3, 3]
    return T_true_44 @ Ds


def rotation_error_parts(T_src_ref_true_44: np.ndarray, T_src_ref_est_44: np.ndarray) -> Tuple[float, float, float]:
    """(total, along, across) rotation error in degrees of an estimated ``T_src_ref``: ``along`` is the error's
    component about ``t x z`` (``t`` the true baseline in the source camera, ``z`` = (0, 0, 1)), the turn that shifts
    the image along the epipolar lines; ``across`` the rest. With no sideways baseline, all of it is ``across``."""
    w = _rotvec(T_src_ref_true_44[:3, :3].T @ T_src_ref_est_44[:3, :3])
    axis = np.cross(T_src_ref_true_44[:3, 3], [0.0, 0.0, 1.0])
    n = float(np.linalg.norm(axis))
    along = abs(float(w @ axis) / n) if n > 1e-12 else 0.0
    total = float(np.linalg.norm(w))
    return tuple(float(np.degrees(x)) for x in (total, along, np.sqrt(max(total ** 2 - along ** 2, 0.0))))


class ScaledErrorRefiner:
    """A pose refiner (the estimator's hook) that hands the plane sweep each source at the true pose relative to the
    reference times the odometry's error scaled by ``rot_scale`` / ``trans_scale``; the reference keeps its odometry
    pose. ``true_pose(stamp)`` gives the ground truth ``T_world_cam`` of a keyframe."""

    def __init__(self, true_pose: Callable[[float], np.ndarray], rot_scale: float, trans_scale: float):
        self.true_pose, self.rot_scale, self.trans_scale = true_pose, float(rot_scale), float(trans_scale)

    def __call__(self, request) -> List[np.ndarray]:
        kfs = request.keyframes
        ref = kfs[request.reference]
        T_w_ref = np.asarray(ref.odom_T_world_cam_44, np.float64)
        G_ref = self.true_pose(ref.stamp)
        out = []
        for kf in kfs:
            T_ref_kf_odo = np.linalg.inv(T_w_ref) @ np.asarray(kf.odom_T_world_cam_44, np.float64)
            T_ref_kf_true = np.linalg.inv(G_ref) @ self.true_pose(kf.stamp)
            out.append(T_w_ref @ scale_error(T_ref_kf_true, T_ref_kf_odo, self.rot_scale, self.trans_scale))
        return out


class ErrorLog:
    """Wraps a pose refiner (or None: the odometry as it is) and records, per source of every window, the rotation
    error parts (:func:`rotation_error_parts`) of the ``T_src_ref`` the plane sweep gets and of the odometry's.
    Other attributes (``last_result``, ``tracking_lost``, ``reset``, counters) are the wrapped refiner's."""

    def __init__(self, inner, true_pose: Callable[[float], np.ndarray]):
        self.inner, self.true_pose = inner, true_pose
        self.rows: List[Tuple[float, ...]] = []

    def __getattr__(self, name):
        if name == 'inner':
            raise AttributeError(name)
        return getattr(self.inner, name)

    def __call__(self, request):
        out = self.inner(request) if self.inner is not None else None
        kfs, r = request.keyframes, request.reference
        used = [np.asarray(T, np.float64) for T in out] if out is not None else \
            [np.asarray(k.T_world_cam_44, np.float64) for k in kfs]
        G_ref = self.true_pose(kfs[r].stamp)
        for i, kf in enumerate(kfs):
            if i == r:
                continue
            true = np.linalg.inv(self.true_pose(kf.stamp)) @ G_ref
            odo = np.linalg.inv(kf.odom_T_world_cam_44) @ kfs[r].odom_T_world_cam_44
            self.rows.append(rotation_error_parts(true, np.linalg.inv(used[i]) @ used[r])
                             + rotation_error_parts(true, odo))
        return out

    def means(self) -> Dict[str, float]:
        keys = ('rot', 'rot_along', 'rot_across', 'odo_rot', 'odo_rot_along', 'odo_rot_across')
        mean = np.mean(self.rows, axis=0) if self.rows else np.full(len(keys), np.nan)
        return {k: float(v) for k, v in zip(keys, mean)}


def _parse_scale(text: str) -> Tuple[float, float]:
    r, _, t = text.partition(':')
    return float(r), float(t) if t else float(r)


def run_row(seq, pose_source: str, row: str) -> Dict[str, Any]:
    """One row (see the module docstring): abs_rel and the sweep's rotation errors."""
    from dpv_sensor.benchmarks import stream_table_inputs as ST
    from dpv_sensor.evaluation import runner as RN
    from dpv_sensor.evaluation.scoring import score_records
    from dpv_sensor.stream.window_refiner import PoseRefinerConfig, WindowPoseRefiner
    stamps = np.asarray(seq.stamps, np.float64)
    gt = [np.asarray(seq.pose(i), np.float64) for i in range(len(seq))]

    def true_pose(stamp: float) -> np.ndarray:
        return gt[int(np.argmin(np.abs(stamps - float(stamp))))]
    overrides: Dict[str, Any] = {'pose_refinement': 'off'}
    inner = None
    if row.startswith('scaled '):
        inner = ScaledErrorRefiner(true_pose, *_parse_scale(row.split(' ', 1)[1]))
    elif row not in ('gt', 'odometry'):
        overrides = {} if row == 'default' else RN.parse_overrides(row.split(','))
    config, _ = RN.build_config(overrides)
    if row not in ('gt', 'odometry') and not row.startswith('scaled ') and config.pose_refinement == 'window':
        inner = WindowPoseRefiner(PoseRefinerConfig.from_params(config.as_dict()))
    log = ErrorLog(inner, true_pose)
    poses = gt if row == 'gt' else ST.odometry_poses(seq, pose_source)
    var = None if row == 'gt' else ST.odometry_variance(seq, pose_source)
    records, _ = RN.run_sequence(seq, config, RN.EvalOptions(progress=False), keep_images=False, poses=poses,
                                 pose_variance=var, pose_refiner=log)
    abs_rel = score_records(records).summary()['metric']['frame_mean']['abs_rel']
    return dict(row=row, abs_rel=float(abs_rel), keyframes=len(records), **log.means())


def markdown(rows: Sequence[Dict[str, Any]]) -> str:
    head = ('| sequence | poses | row | abs_rel | sweep rotation error: total / along / across (deg) | odometry |\n'
            '|---|---|---|---|---|---|\n')
    body = ''.join(f"| {r['sequence']} | {r['poses']} | {r['row']} | {r['abs_rel']:.3f} | {r['rot']:.3f} / "
                   f"{r['rot_along']:.3f} / {r['rot_across']:.3f} | {r['odo_rot']:.3f} / {r['odo_rot_along']:.3f} / "
                   f"{r['odo_rot_across']:.3f} |\n" for r in rows)
    return head + body


def main(argv: Optional[List[str]] = None) -> int:
    from tqdm import tqdm
    from dpv_sensor.benchmarks.stream_table_inputs import add_folder_args, chosen_folders
    from dpv_sensor.cli import tool_argv
    from dpv_sensor.data.sequence import Sequence
    argv = tool_argv(argv)
    p = argparse.ArgumentParser(prog='pose_error_depth', description=__doc__.split('\n\n')[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    add_folder_args(p)
    p.add_argument('--poses', nargs='*', default=['noisy0'], help='pose sources (stream table names: noisy<k>[cov])')
    p.add_argument('--scales', nargs='*', default=['0', '0.6', '1:0'],
                   help='scaled rows: R (rotation and translation) or R:T')
    p.add_argument('--refiners', nargs='*', default=['default'],
                   help="refiner rows: 'default' or KEY=VALUE[,KEY=VALUE] node parameters")
    p.add_argument('--threads', type=int, default=2)
    p.add_argument('--out', type=pathlib.Path, default=pathlib.Path('out/pose_error_depth'))
    a = p.parse_args(argv)
    folders = chosen_folders(p, a)
    names = list(folders)
    for s in a.scales:
        try:
            _parse_scale(s)
        except ValueError:
            p.error(f'--scales {s!r}: not R or R:T')
    import torch
    torch.set_num_threads(a.threads)
    plan = [(n, src, row) for n in names for src in a.poses
            for row in ['gt', 'odometry'] + [f'scaled {s}' for s in a.scales] + list(a.refiners)]
    rows = []
    for n, src, row in tqdm(plan, desc='pose_error_depth', unit='run', dynamic_ncols=True):
        r = dict(sequence=n, poses=src, **run_row(Sequence(folders[n]), src, row))
        rows.append(r)
        tqdm.write(f"{n} {src} {row}: abs_rel {r['abs_rel']:.4f}, sweep rotation error {r['rot']:.3f} deg "
                   f"(odometry {r['odo_rot']:.3f})")
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / 'pose_error_depth.json').write_text(json.dumps(rows, indent=1))
    text = markdown(rows)
    (a.out / 'pose_error_depth.md').write_text(f'Command: `python -m dpv_sensor.studies.pose_error_depth '
                                               f'{" ".join(argv)}`\n\n' + text)
    print('\n' + text)
    return 0


if __name__ == '__main__':
    sys.exit(main())
