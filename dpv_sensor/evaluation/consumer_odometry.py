"""The consumer check: what an RGB-D odometry that consumes the depth camera (Open3D's, with its hybrid and
colour-only Jacobians) makes of the published depth, against the same odometry on the GT depth of the same frames.
No ROS."""
from __future__ import annotations

import logging
import math
from typing import Any, Dict, Iterable, Sequence as SequenceT

import numpy as np

from dpv_sensor.core.pose_math import relative_pose_error_np

LOG = logging.getLogger('dpv_sensor.evaluation.offline')

__all__ = ['CONSUMER_ODOMETRY_DEPTH_MAX', 'consumer_odometry', 'consumer_odometry_text', 'add_consumer_odometry']


# Open3D RGB-D odometry as a consumer runs it: its defaults (image pyramid iterations 20/10/5, depth_diff_max
# 0.03 m), identity initial motion, depth used up to 10 m (Open3D's default of 4 m would cut off most of a
# room-scale view). Two Jacobians: 'hybrid' (Open3D's default: photometric + geometric terms) and 'color'
# (photometric only, the depth only warps); the headline ratio is the hybrid one.
CONSUMER_ODOMETRY_DEPTH_MAX = 10.0
CONSUMER_ODOMETRY_JACOBIANS = ('hybrid', 'color')


def consumer_odometry(records: SequenceT, *, depth_max: float = CONSUMER_ODOMETRY_DEPTH_MAX,
                      jacobians: SequenceT[str] = CONSUMER_ODOMETRY_JACOBIANS,
                      progress: bool = False) -> Dict[str, Any]:
    """How well a real RGB-D consumer tracks on our depth: Open3D's RGB-D odometry between consecutive records,
    once with the predicted depth (no estimate = 0, i.e. no depth) and once with the GT depth of the same frames
    and the same colour images; each estimated motion is compared with the GT relative pose
    (``pose_math.relative_pose_error_np``).

    Returns ``{'pairs', '<jacobian>': {'predicted': {...}, 'gt_depth': {...}, 'ratio_trans', 'ratio_rot'},
    'ratio_trans', 'ratio_rot', 'options'}``: per Jacobian and depth source the median and mean translation /
    rotation RPE (m, deg) and the number of pairs Open3D reported as failed (its motion, the identity, is scored
    as returned: a consumer gets nothing better); ``ratio_*`` = predicted / GT-depth median; the top-level
    ratios are those of the first Jacobian. Pairs without a colour image or a GT pose are skipped.
    """
    from dpv_sensor.evaluation.fusion import open3d
    o3d = open3d()
    od = o3d.pipelines.odometry
    option = od.OdometryOption(depth_max=float(depth_max))
    makers = {'hybrid': od.RGBDOdometryJacobianFromHybridTerm, 'color': od.RGBDOdometryJacobianFromColorTerm}
    for j in jacobians:
        if j not in makers:
            raise ValueError(f'unknown Open3D odometry Jacobian {j!r}; known: {sorted(makers)}')

    def rgbd(image, depth):
        d = np.nan_to_num(np.asarray(depth, np.float32), nan=0.0, posinf=0.0, neginf=0.0)
        d[d < 0] = 0.0
        return o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(np.ascontiguousarray(image, dtype=np.uint8)), o3d.geometry.Image(d),
            depth_scale=1.0, depth_trunc=float(depth_max), convert_rgb_to_intensity=True)

    sides = ('predicted', 'gt_depth')
    errs = {(j, side): [] for j in jacobians for side in sides}
    fails = {(j, side): 0 for j in jacobians for side in sides}
    pairs = [(a, b) for a, b in zip(records[:-1], records[1:])
             if a.image_hw3 is not None and b.image_hw3 is not None and a.gt_T_world_cam_44 is not None
             and b.gt_T_world_cam_44 is not None and a.depth_hw.shape == b.depth_hw.shape]
    iterator: Iterable = pairs
    if progress:
        from tqdm import tqdm
        iterator = tqdm(pairs, desc='consumer odometry', unit='pair', leave=False)
    for a, b in iterator:
        h, w = b.depth_hw.shape
        K = b.K_33
        intr = o3d.camera.PinholeCameraIntrinsic(w, h, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]),
                                                 float(K[1, 2]))
        T_gt = np.linalg.inv(b.gt_T_world_cam_44) @ a.gt_T_world_cam_44     # maps a's camera points into b's
        for side, da, db in (('predicted', a.depth_hw, b.depth_hw), ('gt_depth', a.gt_depth_hw, b.gt_depth_hw)):
            src, dst = rgbd(a.image_hw3, da), rgbd(b.image_hw3, db)
            for j in jacobians:
                ok, T_est, _info = od.compute_rgbd_odometry(src, dst, intr, np.eye(4), makers[j](), option)
                if not ok:
                    fails[(j, side)] += 1
                errs[(j, side)].append(relative_pose_error_np(T_gt, np.asarray(T_est)))
    out: Dict[str, Any] = {'pairs': len(pairs), 'options': {'jacobians': list(jacobians),
                                                             'depth_max_m': float(depth_max),
                                                             'depth_diff_max_m': float(option.depth_diff_max),
                                                             'init': 'identity'}}
    for j in jacobians:
        res: Dict[str, Any] = {}
        for side in sides:
            arr = np.asarray(errs[(j, side)], np.float64).reshape(-1, 2)
            n = len(arr)
            res[side] = {'trans_m_median': float(np.median(arr[:, 0])) if n else float('nan'),
                         'rot_deg_median': float(np.median(arr[:, 1])) if n else float('nan'),
                         'trans_m_mean': float(arr[:, 0].mean()) if n else float('nan'),
                         'rot_deg_mean': float(arr[:, 1].mean()) if n else float('nan'),
                         'failures': fails[(j, side)]}
        for key, name in (('trans_m_median', 'ratio_trans'), ('rot_deg_median', 'ratio_rot')):
            p, g = res['predicted'][key], res['gt_depth'][key]
            res[name] = p / g if math.isfinite(p) and math.isfinite(g) and g > 0 else float('nan')
        out[j] = res
    if jacobians:
        out['ratio_trans'] = out[jacobians[0]]['ratio_trans']
        out['ratio_rot'] = out[jacobians[0]]['ratio_rot']
    return out


def consumer_odometry_text(summary: Dict[str, Any]) -> str:
    """Lines for the user: per Open3D Jacobian, the median RPE of the consumer odometry on predicted vs GT depth
    (empty when the summary has none)."""
    co = summary.get('consumer_odometry') or {}
    lines = []
    if 'error' in co:
        lines.append(f"consumer odometry skipped: {co['error']}")
    for j in (co.get('options') or {}).get('jacobians', []):
        r = co[j]
        p, g = r['predicted'], r['gt_depth']
        lines.append(f"consumer odometry ({j}, {co['pairs']} pairs of consecutive outputs): median translation / "
                     f"rotation error {p['trans_m_median'] * 100:.2f} cm / {p['rot_deg_median']:.2f} deg on the "
                     f"predicted depth, {g['trans_m_median'] * 100:.2f} cm / {g['rot_deg_median']:.2f} deg on the GT "
                     f"depth: {r['ratio_trans']:.2f}x / {r['ratio_rot']:.2f}x")
    return ''.join('\n' + line for line in lines) + ('\n' if lines else '')


def add_consumer_odometry(summary: Dict[str, Any], records, options) -> None:
    """summary['consumer_odometry'] when asked for; an Open3D failure is reported there, not raised."""
    if not options.consumer_odometry or len(records) < 2:
        return
    try:
        summary['consumer_odometry'] = consumer_odometry(records, progress=options.progress)
    except Exception as exc:   # e.g. Open3D cannot load on this machine: the depth scores still stand
        LOG.warning('consumer odometry skipped: %s: %s', type(exc).__name__, exc)
        summary['consumer_odometry'] = {'error': f'{type(exc).__name__}: {exc}'}
