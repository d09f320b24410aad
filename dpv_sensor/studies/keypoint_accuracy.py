"""How far the window refiner's keypoint relative poses really err, against what their covariance says.

    .venv/bin/python -m dpv_sensor.studies.keypoint_accuracy --data DATA [--seeds 60,61,62,63] [--json OUT]
        [--detector orb]

The refiner's keypoint factors (``core.keypoint_pose``) carry the Gauss-Newton covariance of the inliers' Sampson
distances. This tool measures whether that covariance is honest on the pairs the node actually builds: keyframes
chosen by the node's keyframe selector (default thresholds) on the ground-truth poses, images resized to the
processing size as the estimator does, and each keyframe paired with its ``keypoint_sources`` nearest earlier
keyframes, matched with the refiner's keypoint settings. For every pair with an estimate it compares

- the rotation with the ground truth's: ``d = Log(R_kp R_gt^T)`` (radians, left increment, the covariance's
  convention) and its normalised squared error ``NEES = d^T S^-1 d`` (3 dof: 2.37 is the median of an honest
  covariance, 7.81 its 95 % point);
- the translation direction likewise in the covariance's 2-dof tangent basis (median 1.39, 95 % 5.99).

It prints, per sequence and per bin of inliers and of parallax, for the rotation, the direction and the rotation
given the true direction (what the window's graph gets where the odometry pins the direction: the linear
conditional of the estimate and its covariance), the median error and the median std the covariance says
(degrees), the median NEES and the share of pairs beyond the honest 95 % point. Then it fits the floors the refiner
can add (``KeypointConfig.rotation_floor_deg`` / ``direction_floor_deg``, in quadrature on each axis) so that the
median NEES of the direction and of the rotation given the direction are the honest ones (a median, because gross
errors from repeated texture are the window's Huber kernel's to handle) on the rendered sequences, whose poses
are exact, and prints the NEES under them; with ``--loso`` the fit leaving each
sequence out. The datasets' own pose errors (SUN3D's about 0.5 deg, TUM's motion blur and sync) are part of what
is measured on real data, so only the rendered sequences tell the keypoints' own error.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import pathlib
import sys
from dataclasses import asdict, dataclass
from typing import Dict, Iterable, List, Optional, Sequence as Seq, Tuple

import cv2
import numpy as np

from dpv_sensor import params as P
from dpv_sensor.common import to_jsonable
from dpv_sensor.core.flow_rotation import FlowConfig, flow_matches, match_image, rotation_given_direction
from dpv_sensor.core.keypoint_pose import (KeypointConfig, KeypointPose, detect_features, keypoint_relative_pose,
                                           rotation_given_direction_gain)

CHI2_MEDIAN = {3: 2.366, 2: 1.386}
CHI2_95 = {2: 5.991, 3: 7.815, 5: 11.070}
RENDERED_PREFIXES = ('synthetic', 'icl_nuim', 'tartanair')
INLIER_BINS = (20, 40, 80, 160, 10 ** 9)
PARALLAX_BINS = (0.0, 2.0, 5.0, 15.0, math.inf)


@dataclass
class PairError:
    """One keyframe pair: its inliers and parallax, the error of (rotation, direction) against the ground truth in
    the covariance's coordinates (radians: a left rotation increment, then the direction's 2-dof increment; the
    rotation alone where the parallax gave no direction) and the estimate's covariance of the same."""
    sequence: str
    ref: int
    src: int
    inliers: int
    parallax_px: float
    baseline_m: float
    err: List[float]
    cov: List[List[float]]

    @property
    def has_direction(self) -> bool:
        return len(self.err) == 5


def floors(n: int, rot_deg: float, dir_deg: float) -> np.ndarray:
    """The floors' diagonal covariance for an error of ``n`` (3 or 5) components."""
    return np.diag(np.radians([rot_deg] * 3 + [dir_deg] * (n - 3))) ** 2


def blocks(r: PairError, rot_deg: float = 0.0, dir_deg: float = 0.0):
    """(rotation error, its covariance), (direction ...), (rotation given the true direction ...) with the floors
    added; the last two None without a direction. The conditional is what the window's graph gets where the
    odometry pins the direction: ``d_r - S_rd S_dd^-1 d_d`` with covariance ``S_rr - S_rd S_dd^-1 S_dr``."""
    e = np.asarray(r.err, np.float64)
    S = np.asarray(r.cov, np.float64) + floors(len(e), rot_deg, dir_deg)
    rot = (e[:3], S[:3, :3])
    if not r.has_direction:
        return rot, None, None
    G, cov_cond = rotation_given_direction_gain(S)
    return rot, (e[3:], S[3:, 3:]), (e[:3] - G @ e[3:], cov_cond)


def keyframe_indices(poses_n44: np.ndarray) -> List[int]:
    """The frames the node's keyframe selector (default thresholds) takes on these poses."""
    from dpv_sensor.stream.keyframes import KeyframeSelector
    sel = KeyframeSelector(P.default('keyframe_translation'), P.default('keyframe_rotation_deg'),
                           P.default('keyframe_max_interval'))
    return [i for i, T in enumerate(poses_n44) if sel.decide(T).is_keyframe]


def _log_so3(R: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(R, np.float64))[0].ravel()


def pair_error(name: str, ref: int, src: int, kp: KeypointPose, T_src_ref_gt: np.ndarray) -> PairError:
    """Errors of one keypoint estimate ``T_src_ref`` (views a = ref, b = src) against the ground truth."""
    R_gt, t_gt = T_src_ref_gt[:3, :3], T_src_ref_gt[:3, 3]
    err = _log_so3(kp.R_b_a @ R_gt.T)
    cov = kp.rotation_covariance()
    if kp.t_dir_b is not None and kp.cov_55 is not None and np.linalg.norm(t_gt) > 0:
        u = t_gt / np.linalg.norm(t_gt)
        # t_kp = normalise(t_true + B d): d = B^T (t_kp - t_true) to first order, B normal to t_kp
        err = np.r_[err, kp.basis_32.T @ (np.asarray(kp.t_dir_b) - u)]
        cov = kp.cov_55
    return PairError(name, ref, src, kp.inliers, kp.parallax_px, float(np.linalg.norm(t_gt)), err.tolist(),
                     np.asarray(cov).tolist())


def sequence_pairs(name: str, images: Iterable[np.ndarray], K_33: np.ndarray, poses_n44: np.ndarray,
                   sources: int, config: KeypointConfig, flow: Optional[FlowConfig] = None
                   ) -> Tuple[List[PairError], int]:
    """Every keyframe paired with its ``sources`` nearest earlier keyframes; (errors of the estimates, pairs tried).
    ``images`` yields the keyframes' images in order, at the size ``K_33`` belongs to. With ``flow`` the pairs'
    rotations come from :mod:`dpv_sensor.core.flow_rotation` given the true direction instead (:func:`flow_pair`)."""
    kfs = keyframe_indices(poses_n44)
    feats, out, tried = [], [], 0
    for j, (i, img) in enumerate(zip(kfs, images)):
        feats.append(match_image(img, K_33, flow) if flow is not None else detect_features(img, config))
        for g in range(1, sources + 1):
            if j - g < 0:
                break
            s = kfs[j - g]
            tried += 1
            T_src_ref = np.linalg.inv(poses_n44[s]) @ poses_n44[i]
            if flow is not None:
                row = flow_pair(name, i, s, feats[j], feats[j - g], T_src_ref, flow)
                if row is not None:
                    out.append(row)
                continue
            kp = keypoint_relative_pose(feats[j], feats[j - g], K_33, config)
            if not kp.ok:
                continue
            out.append(pair_error(name, i, s, kp, T_src_ref))
    return out, tried


#: the rotation error (deg) the flow pairs start from, about an axis drawn per pair: the odometry's, roughly
FLOW_START_ERROR_DEG = 0.5


def flow_pair(name: str, ref: int, src: int, ref_image, src_image, T_src_ref_gt: np.ndarray,
              config: FlowConfig) -> Optional[PairError]:
    """The flow rotation of one pair (views a = ref, b = src; ``(grey, K)`` from ``match_image``) given the true
    translation direction, started :data:`FLOW_START_ERROR_DEG` off the truth, as a 3-dof :class:`PairError`; None
    when it gives no estimate."""
    rng = np.random.default_rng(ref * 100003 + src)
    axis = rng.normal(size=3)
    start = cv2.Rodrigues(axis / np.linalg.norm(axis) * math.radians(FLOW_START_ERROR_DEG))[0] @ T_src_ref_gt[:3, :3]
    matches = flow_matches(ref_image[0], src_image[0], ref_image[1], config)
    est = rotation_given_direction(matches, T_src_ref_gt[:3, 3], start, config)
    if not est.ok:
        return None
    err = _log_so3(est.R_b_a @ T_src_ref_gt[:3, :3].T)
    return PairError(name, ref, src, est.inliers, 0.0, float(np.linalg.norm(T_src_ref_gt[:3, 3])), err.tolist(),
                     np.asarray(est.cov_33).tolist())


# ------------------------------------------------------------------------------------------------------------------
# the covariance model (KeypointConfig's floors added to the inliers' covariance) and its fit

def nees(err, cov) -> float:
    """d^T S^-1 d; inf where S is singular (a covariance that calls some direction exact)."""
    d = np.asarray(err, np.float64)
    try:
        return float(d @ np.linalg.solve(np.asarray(cov, np.float64), d))
    except np.linalg.LinAlgError:
        return math.inf


def _nees_rows(errs: np.ndarray, covs: np.ndarray) -> np.ndarray:
    """:func:`nees` of every row (``errs`` (n, k), ``covs`` (n, k, k)) at once; inf where a covariance is
    singular, as :func:`nees` gives."""
    try:
        x = np.linalg.solve(covs, errs[:, :, None])[:, :, 0]
    except np.linalg.LinAlgError:                                          # one singular: row by row, as nees does
        return np.asarray([nees(e, S) for e, S in zip(errs, covs)])
    return np.asarray([float(e @ v) for e, v in zip(errs, x)])


def fit_floors(rows: Seq[PairError]) -> Tuple[float, float]:
    """(rotation, direction) floors in degrees at which the median NEES of the direction and of the rotation given
    the direction are the honest medians (1.39 and 2.37): a median is blind to the gross errors (repeated texture
    matched one period off) that the window's Huber kernel is there for, where a likelihood would widen the core for
    them. A grid, then a finer one around the best."""
    rows = [r for r in rows if r.has_direction]
    if not rows:
        return 0.0, 0.0

    errs = np.asarray([r.err for r in rows], np.float64)                  # (n, 5)
    covs = np.asarray([r.cov for r in rows], np.float64)                  # (n, 5, 5)

    def cost(br, bd):
        # blocks() and nees() on every row at once (the same LAPACK and BLAS calls per matrix, so the same numbers)
        S = covs + floors(5, br, bd)
        e_dir, S_dir = errs[:, 3:], S[:, 3:, 3:]
        G = S[:, :3, 3:] @ np.linalg.pinv(S_dir)
        cov_cond = S[:, :3, :3] - G @ S[:, 3:, :3]
        cov_cond = 0.5 * (cov_cond + np.swapaxes(cov_cond, -1, -2))
        e_cond = errs[:, :3] - (G @ e_dir[:, :, None])[:, :, 0]
        med_dir = float(np.median(_nees_rows(e_dir, S_dir)))
        med_cond = float(np.median(_nees_rows(e_cond, cov_cond)))
        return math.log(med_dir / CHI2_MEDIAN[2]) ** 2 + math.log(med_cond / CHI2_MEDIAN[3]) ** 2

    def search(grid_r, grid_d):
        return min((cost(br, bd), br, bd) for br in grid_r for bd in grid_d)[1:]
    br, bd = search(np.r_[0.0, np.geomspace(0.01, 3.0, 16)], np.r_[0.0, np.geomspace(0.1, 30.0, 16)])
    br, bd = search(np.r_[0.0, np.geomspace(max(br / 1.5, 0.005), max(br * 1.5, 0.01), 9)],
                    np.r_[0.0, np.geomspace(max(bd / 1.5, 0.05), max(bd * 1.5, 0.1), 9)])
    return float(br), float(bd)


# ------------------------------------------------------------------------------------------------------------------
# tables

def _bin_label(edges, i) -> str:
    lo, hi = edges[i], edges[i + 1]
    return f'{lo:g}+' if not math.isfinite(hi) or hi >= 10 ** 9 else f'{lo:g}-{hi:g}'


def summary(rows: List[PairError], fitted: Optional[Tuple[float, float]] = None) -> Dict[str, float]:
    """Per block (rotation, direction, rotation given the true direction): median error and median std the
    covariance says (deg), median NEES and the share beyond the honest 95 % point; with ``fitted`` floors the NEES
    of the rotation given the direction and the share beyond 95 % under them."""
    if not rows:
        return {'pairs': 0}
    out: Dict[str, float] = {'pairs': len(rows)}
    parts = [blocks(r) for r in rows]
    for i, name in enumerate(('rot', 'dir', 'cond')):
        got = [p[i] for p in parts if p[i] is not None]
        if not got:
            continue
        n = len(got[0][0])
        ns = np.asarray([nees(e, S) for e, S in got])
        stds = [math.sqrt(max(float(np.trace(S)) / n, 0.0)) for _, S in got]     # >= 0 against rounding
        out.update({f'{name}_err_deg': float(np.degrees(np.median([np.linalg.norm(e) for e, _ in got]))),
                    f'{name}_sigma_deg': float(np.degrees(np.median(stds))),
                    f'{name}_nees_median': float(np.median(ns)), f'{name}_beyond95': float(np.mean(ns > CHI2_95[n]))})
    if fitted:
        got = [blocks(r, *fitted)[2] for r in rows if r.has_direction]
        if got:
            ns = np.asarray([nees(e, S) for e, S in got])
            out.update(fit_cond_nees_median=float(np.median(ns)), fit_cond_beyond95=float(np.mean(ns > CHI2_95[3])))
    return out


def _fmt(s: Dict[str, float], key: str, spec: str = '.3f') -> str:
    v = s.get(key)
    return '' if v is None else format(v, spec)


def table(groups: Dict[str, List[PairError]], tried: Dict[str, int], fitted=None) -> str:
    """Error (median) / std said (median), in degrees, then NEES median and share beyond 95 %, per block."""
    head = ('| group | pairs (of tried) | rotation: err / std (deg); NEES, beyond 95 % | direction: the same | '
            'rotation given the direction: the same' + (' | with the fitted floors: NEES, beyond 95 %' if fitted
                                                         else '') + ' |')
    lines = [head, '|' + '---|' * (head.count('|') - 1)]
    for name, rows in groups.items():
        s = summary(rows, fitted)
        t = tried.get(name)
        cells = [name, f"{s['pairs']}" + (f' ({t})' if t else '')]
        for b in ('rot', 'dir', 'cond'):
            cells.append('' if f'{b}_err_deg' not in s else
                         f"{s[f'{b}_err_deg']:.2f} / {s[f'{b}_sigma_deg']:.2f}; {s[f'{b}_nees_median']:.1f}, "
                         f"{s[f'{b}_beyond95']:.0%}")
        if fitted:
            cells.append(f"{_fmt(s, 'fit_cond_nees_median', '.1f')}, {_fmt(s, 'fit_cond_beyond95', '.0%')}")
        lines.append('| ' + ' | '.join(cells) + ' |')
    return '\n'.join(lines)


def binned(rows: List[PairError]) -> Dict[str, List[PairError]]:
    groups: Dict[str, List[PairError]] = {}
    for i in range(len(INLIER_BINS) - 1):
        groups[f'inliers {_bin_label(INLIER_BINS, i)}'] = [
            r for r in rows if INLIER_BINS[i] <= r.inliers < INLIER_BINS[i + 1]]
    for i in range(len(PARALLAX_BINS) - 1):
        groups[f'parallax {_bin_label(PARALLAX_BINS, i)} px'] = [
            r for r in rows if PARALLAX_BINS[i] <= r.parallax_px < PARALLAX_BINS[i + 1]]
    return {k: v for k, v in groups.items() if v}


# ------------------------------------------------------------------------------------------------------------------

def _sequences(data: Optional[pathlib.Path], names: Seq[str], seeds: Seq[int], frames: int):
    """(name, sequence) of the data folder's sequences and the rendered seeds."""
    from dpv_sensor.benchmarks.stream_table_inputs import RENDER_SIZE, sequence_folders
    from dpv_sensor.data.sequence import Sequence
    if data is not None:
        for folder in sequence_folders(data):
            if names and folder.name not in names:
                continue
            seq = Sequence(folder)
            yield folder.name, seq
    for seed in seeds:
        from dpv_sensor.data.synthetic import render_sequence
        yield f'synthetic_seed{seed}', render_sequence(seed, frames, width=RENDER_SIZE[0], height=RENDER_SIZE[1],
                                                       lazy=True)


def is_rendered(name: str) -> bool:
    return name.startswith(RENDERED_PREFIXES)


def main(argv: Optional[List[str]] = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0], epilog=__doc__.split('\n\n', 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--data', type=pathlib.Path, help='a folder of sequence folders (e.g. the shared data)')
    p.add_argument('--sequences', nargs='*', default=[], help='only these sequence folders')
    p.add_argument('--seeds', default='60,61,62,63', help='rendered scenes (comma separated; none: empty)')
    p.add_argument('--frames', type=int, default=120, help='frames of each rendered scene')
    p.add_argument('--sources', type=int, default=2, help="pairs per keyframe (the refiner's keypoint_sources)")
    p.add_argument('--size', help="match at this WxH (default: the node's processing size; 'full': the images' own)")
    p.add_argument('--detector', choices=('sift', 'orb'), default=KeypointConfig().detector,
                   help="keypoints and descriptors (default: the refiner's)")
    p.add_argument('--matcher', choices=('keypoints', 'flow'), default='keypoints',
                   help="keypoints (the detector's), or flow: the window's flow rotation given the true direction "
                        "(at the camera's resolution unless --size; its rotation column is that rotation) and the "
                        "covariance_scale that makes its median NEES honest on the rendered sequences")
    p.add_argument('--flow-variational-iterations', type=int, default=None,
                   help="with --matcher flow: DIS's variational refinement iterations per scale (default: the "
                        "preset's)")
    p.add_argument('--flow-patch-stride', type=int, default=None,
                   help="with --matcher flow: DIS's step between patches in pixels (default: the preset's)")
    p.add_argument('--flow-converged-rad', type=float, default=FlowConfig().converged_rad,
                   help='with --matcher flow: the rotation fit stops once a Gauss-Newton step is below this (rad)')
    p.add_argument('--loso', action='store_true', help='also fit leaving each sequence out')
    p.add_argument('--json', type=pathlib.Path, help='write every pair and the fits here')
    a = p.parse_args(argv)
    from tqdm import tqdm
    size = (P.default('processing_width'), P.default('processing_height'))
    flow = FlowConfig(variational_iterations=a.flow_variational_iterations, patch_stride=a.flow_patch_stride,
                      converged_rad=a.flow_converged_rad) if a.matcher == 'flow' else None
    if flow is not None:
        size = None
    if a.size:
        size = None if a.size == 'full' else tuple(int(v) for v in a.size.lower().split('x'))
    seeds = [int(s) for s in a.seeds.split(',') if s.strip()]
    config = dataclasses.replace(KeypointConfig(), rotation_floor_deg=0.0, direction_floor_deg=0.0,  # S_kp raw
                                 detector=a.detector)
    rows: Dict[str, List[PairError]] = {}
    tried: Dict[str, int] = {}
    for name, seq in _sequences(a.data, a.sequences, seeds, a.frames):
        if size is not None and tuple(seq.size) != size:
            seq = seq.resized(*size)           # as the estimator resizes (interpolation and K alike)
        poses = np.asarray(seq.poses, np.float64)
        kfs = keyframe_indices(poses)
        images = (seq.image(i) for i in tqdm(kfs, desc=name, unit='keyframe', leave=False))
        rows[name], tried[name] = sequence_pairs(name, images, seq.K, poses, a.sources, config, flow)
    if not rows:
        p.error('no sequences: give --data or --seeds')
    if flow is not None:
        return _flow_report(rows, tried, flow, a.json)
    every = [r for v in rows.values() for r in v]
    rendered = [r for r in every if is_rendered(r.sequence)]
    fitted = fit_floors(rendered) if rendered else None
    print("## The inliers' covariance (no floors); NEES: honest medians 2.37 (3 dof), 1.39 (2 dof)\n")
    print(table(rows, tried, fitted))
    if fitted:
        print(f'\nfloors fitted on the rendered sequences ({len(rendered)} pairs): rotation {fitted[0]:.3g} deg, '
              f'direction {fitted[1]:.3g} deg (the default KeypointConfig: {KeypointConfig().rotation_floor_deg:g} / '
              f'{KeypointConfig().direction_floor_deg:g})')
    print('\n## By inliers and parallax, rendered sequences\n')
    print(table(binned(rendered), {}, fitted))
    real = [r for r in every if not is_rendered(r.sequence)]
    if real:
        print('\n## By inliers and parallax, real sequences (their ground truth has errors of its own)\n')
        print(table(binned(real), {}, fitted))
    loso = {}
    if a.loso:
        print('\n## Leave one sequence out (floors fitted on all others, NEES on the one left out)\n')
        for name in rows:
            f = fit_floors([r for r in every if r.sequence != name])
            s = summary(rows[name], f)
            loso[name] = {'floors_deg': f, 'summary': s}
            print(f"{name}: floors {f[0]:.3g} / {f[1]:.3g} deg; rotation given direction NEES "
                  f"{_fmt(s, 'fit_cond_nees_median', '.2f')}, beyond 95 % {_fmt(s, 'fit_cond_beyond95', '.0%')}")
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(to_jsonable({'detector': a.detector, 'pairs': [asdict(r) for r in every],
                                                  'tried': tried,
                                                  'floors_rendered_deg': fitted, 'loso': loso}), indent=1))
        print(f'\nwritten: {a.json}')
    return 0


def _flow_report(rows: Dict[str, List[PairError]], tried: Dict[str, int], flow: FlowConfig,
                 json_out: Optional[pathlib.Path]) -> int:
    """The flow rotations' table and the covariance scale fitted on the rendered sequences."""
    print(f'## Flow rotation given the true direction (covariance_scale {flow.covariance_scale:g}); NEES: honest '
          f'median 2.37 (3 dof)\n')
    print(table(rows, tried))
    rendered = [r for v in rows.values() for r in v if is_rendered(r.sequence)]
    fitted = None
    if rendered:
        med = float(np.median([nees(r.err, r.cov) for r in rendered]))
        fitted = flow.covariance_scale * med / CHI2_MEDIAN[3]
        print(f'\ncovariance_scale that gives the rendered sequences ({len(rendered)} pairs) the honest median NEES: '
              f'{fitted:.3g}')
    if json_out:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(json.dumps(to_jsonable({'matcher': 'flow', 'covariance_scale': flow.covariance_scale,
                                                    'fitted_covariance_scale': fitted, 'tried': tried,
                                                    'pairs': [asdict(r) for v in rows.values() for r in v]}),
                                       indent=1))
        print(f'\nwritten: {json_out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
