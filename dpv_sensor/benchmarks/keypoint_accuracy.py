"""How far the window refiner's keypoint relative poses really err, against what their covariance says.

    .venv/bin/python -m dpv_sensor.benchmarks.keypoint_accuracy --data DATA [--seeds 60,61,62,63] [--json OUT]

The refiner's keypoint factors (``core.keypoint_pose``) carry the Gauss-Newton covariance of the inliers' Sampson
distances. This tool measures whether that covariance is honest on the pairs the node actually builds: keyframes
chosen by the node's keyframe selector (default thresholds) on the ground-truth poses, images resized to the
processing size as the estimator does, and each keyframe paired with its ``keypoint_sources`` nearest earlier
keyframes, matched with the refiner's keypoint settings. For every pair with an estimate it compares

- the rotation with the ground truth's: ``d = Log(R_kp R_gt^T)`` (radians, left increment, the covariance's
  convention) and its normalised squared error ``NEES = d^T S^-1 d`` (3 dof: 2.37 is the median of an honest
  covariance, 7.81 its 95 % point);
- the translation direction likewise in the covariance's 2-dof tangent basis (median 1.39, 95 % 5.99).

It prints, per sequence and per bin of inliers and of parallax, the median rotation error and the median predicted
std (degrees), the median NEES, and the share of pairs beyond the honest 95 % point. Then it fits the
covariance model the refiner can apply, ``S = a^2 S_kp + b^2 I`` per block (a factor on the inliers' covariance and
a floor in degrees), by the likelihood of a Huber-robust Gaussian (the refiner's factors are Huber too), on the
rendered sequences (exact poses) and reports the NEES of the fitted model on each real sequence; with
``--loso`` also the fit leaving each sequence out. The datasets' own pose errors (SUN3D's are about 0.2 deg) are
part of what is measured on real data, so the rendered fit is the one to use.
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
from dpv_sensor.core.keypoint_pose import KeypointConfig, KeypointPose, detect_features, keypoint_relative_pose

CHI2_MEDIAN = {3: 2.366, 2: 1.386}
CHI2_95 = {3: 7.815, 2: 5.991}
RENDERED_PREFIXES = ('synthetic', 'icl_nuim', 'tartanair')
INLIER_BINS = (20, 40, 80, 160, 10 ** 9)
PARALLAX_BINS = (0.0, 2.0, 5.0, 15.0, math.inf)


@dataclass
class PairError:
    """One keyframe pair: its inliers and parallax, the rotation and direction errors against the ground truth
    (radians, in the covariance's axes) and the predicted covariance blocks."""
    sequence: str
    ref: int
    src: int
    inliers: int
    parallax_px: float
    baseline_m: float
    rot_err_3: List[float]
    rot_cov_33: List[List[float]]
    dir_err_2: Optional[List[float]] = None
    dir_cov_22: Optional[List[List[float]]] = None
    # the rotation given the true direction (what the graph gets where the odometry pins the direction): the
    # linear conditional of the 5-dof estimate, its error and covariance
    cond_err_3: Optional[List[float]] = None
    cond_cov_33: Optional[List[List[float]]] = None

    @property
    def rot_deg(self) -> float:
        return math.degrees(float(np.linalg.norm(self.rot_err_3)))

    @property
    def rot_sigma_deg(self) -> float:
        return math.degrees(math.sqrt(float(np.trace(np.asarray(self.rot_cov_33))) / 3.0))


def keyframe_indices(poses_n44: np.ndarray) -> List[int]:
    """The frames the node's keyframe selector (default thresholds) takes on these poses."""
    from dpv_sensor.stream.keyframes import KeyframeSelector
    sel = KeyframeSelector(P.default('keyframe_translation'), P.default('keyframe_rotation_deg'),
                           P.default('keyframe_max_interval'))
    return [i for i, T in enumerate(poses_n44) if sel.decide(T).is_keyframe]


def processing_image(image: np.ndarray, K_33: np.ndarray, size: Tuple[int, int]) -> Tuple[np.ndarray, np.ndarray]:
    """The image and K at the processing size, resized as the estimator does."""
    from dpv_sensor.core.geometry import scale_intrinsics_np
    W, H = size
    h0, w0 = image.shape[:2]
    if (w0, h0) != (W, H):
        image = cv2.resize(image, (W, H), interpolation=cv2.INTER_AREA if (W <= w0 and H <= h0) else cv2.INTER_LINEAR)
    return image, scale_intrinsics_np(K_33, W / w0, H / h0)


def _log_so3(R: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(R, np.float64))[0].ravel()


def pair_error(name: str, ref: int, src: int, kp: KeypointPose, T_src_ref_gt: np.ndarray) -> PairError:
    """Errors of one keypoint estimate ``T_src_ref`` (views a = ref, b = src) against the ground truth."""
    R_gt, t_gt = T_src_ref_gt[:3, :3], T_src_ref_gt[:3, 3]
    d_rot = _log_so3(kp.R_b_a @ R_gt.T)
    out = PairError(name, ref, src, kp.inliers, kp.parallax_px, float(np.linalg.norm(t_gt)), d_rot.tolist(),
                    kp.rotation_covariance().tolist())
    if kp.t_dir_b is not None and kp.cov_55 is not None and np.linalg.norm(t_gt) > 0:
        u = t_gt / np.linalg.norm(t_gt)
        # t_kp = normalise(t_true + B d): d = B^T (t_kp - t_true) to first order, B normal to t_kp
        out.dir_err_2 = (kp.basis_32.T @ (np.asarray(kp.t_dir_b) - u)).tolist()
        out.dir_cov_22 = kp.cov_55[3:, 3:].tolist()
        C = np.asarray(kp.cov_55, np.float64)
        G = C[:3, 3:] @ np.linalg.pinv(C[3:, 3:])
        out.cond_err_3 = (d_rot - G @ np.asarray(out.dir_err_2)).tolist()
        out.cond_cov_33 = (C[:3, :3] - G @ C[3:, :3]).tolist()
    return out


def sequence_pairs(name: str, images: Iterable[np.ndarray], K_33: np.ndarray, poses_n44: np.ndarray,
                   size: Tuple[int, int], sources: int, config: KeypointConfig) -> Tuple[List[PairError], int]:
    """Every keyframe paired with its ``sources`` nearest earlier keyframes; (errors of the estimates, pairs tried).
    ``images`` yields the keyframes' images in order."""
    kfs = keyframe_indices(poses_n44)
    feats, out, tried = [], [], 0
    for j, (i, img) in enumerate(zip(kfs, images)):
        img_p, K = processing_image(img, K_33, size)
        feats.append(detect_features(img_p, config))
        for g in range(1, sources + 1):
            if j - g < 0:
                break
            s = kfs[j - g]
            tried += 1
            kp = keypoint_relative_pose(feats[j], feats[j - g], K, config)
            if not kp.ok:
                continue
            T_src_ref = np.linalg.inv(poses_n44[s]) @ poses_n44[i]
            out.append(pair_error(name, i, s, kp, T_src_ref))
    return out, tried


# ------------------------------------------------------------------------------------------------------------------
# the covariance model S = a^2 S_kp + b^2 I and its fit

def nees(err: Seq[float], cov, a: float = 1.0, b_rad: float = 0.0) -> float:
    d = np.asarray(err, np.float64)
    S = a * a * np.asarray(cov, np.float64) + b_rad * b_rad * np.eye(len(d))
    return float(d @ np.linalg.solve(S, d))


def _huber_nll(err: Seq[float], cov, a: float, b_rad: float, k: float) -> float:
    """Negative log-likelihood of a Huber-robust Gaussian (up to a constant): 0.5 log det S + rho(sqrt(NEES))."""
    d = np.asarray(err, np.float64)
    S = a * a * np.asarray(cov, np.float64) + b_rad * b_rad * np.eye(len(d))
    r = math.sqrt(max(float(d @ np.linalg.solve(S, d)), 0.0))
    rho = 0.5 * r * r if r <= k else k * (r - 0.5 * k)
    return 0.5 * float(np.linalg.slogdet(S)[1]) + rho


def fit_model(pairs: Seq[Tuple[Seq[float], object]], k: float = 1.345) -> Tuple[float, float]:
    """(a, b in degrees) of ``S = a^2 S_kp + b^2 I`` maximising the Huber likelihood of ``pairs`` (err, cov);
    a grid search (a from 1 to 1000, b from 0 to 30 deg), then a finer one around the best."""
    pairs = [(e, c) for e, c in pairs]
    if not pairs:
        return 1.0, 0.0

    def cost(a, b_deg):
        return sum(_huber_nll(e, c, a, math.radians(b_deg), k) for e, c in pairs)
    grid_a = np.geomspace(1.0, 1000.0, 25)
    grid_b = np.r_[0.0, np.geomspace(0.005, 30.0, 36)]
    best = min(((cost(a, b), a, b) for a in grid_a for b in grid_b))
    _, a0, b0 = best
    fine_a = np.geomspace(max(a0 / 1.4, 1.0), a0 * 1.4, 9)
    fine_b = np.r_[0.0, np.geomspace(max(b0 / 1.4, 1e-3), max(b0 * 1.4, 2e-3), 9)]
    best = min(((cost(a, b), a, b) for a in fine_a for b in fine_b))
    return float(best[1]), float(best[2])


# ------------------------------------------------------------------------------------------------------------------
# tables

def _bin_label(edges, i) -> str:
    lo, hi = edges[i], edges[i + 1]
    return f'{lo:g}+' if not math.isfinite(hi) or hi >= 10 ** 9 else f'{lo:g}-{hi:g}'


def summary(rows: List[PairError], model: Optional[Dict[str, Tuple[float, float]]] = None) -> Dict[str, float]:
    """Median rotation error and predicted std (deg), median NEES and the share beyond the honest 95 % point, for
    the rotation and (where measured) the direction; with ``model`` also the NEES under the fitted model."""
    if not rows:
        return {'pairs': 0}
    rot_nees = [nees(r.rot_err_3, r.rot_cov_33) for r in rows]
    out = {'pairs': len(rows), 'rot_err_deg': float(np.median([r.rot_deg for r in rows])),
           'rot_err_p90_deg': float(np.percentile([r.rot_deg for r in rows], 90)),
           'rot_sigma_deg': float(np.median([r.rot_sigma_deg for r in rows])),
           'rot_nees_median': float(np.median(rot_nees)),
           'rot_beyond95': float(np.mean(np.asarray(rot_nees) > CHI2_95[3]))}
    dirs = [r for r in rows if r.dir_err_2 is not None]
    if dirs:
        dn = [nees(r.dir_err_2, r.dir_cov_22) for r in dirs]
        out.update(dir_err_deg=float(np.degrees(np.median([np.linalg.norm(r.dir_err_2) for r in dirs]))),
                   dir_sigma_deg=float(np.degrees(np.median([math.sqrt(np.trace(np.asarray(r.dir_cov_22)) / 2)
                                                             for r in dirs]))),
                   dir_nees_median=float(np.median(dn)), dir_beyond95=float(np.mean(np.asarray(dn) > CHI2_95[2])))
    conds = [r for r in rows if r.cond_err_3 is not None]
    if conds:
        cn = [nees(r.cond_err_3, r.cond_cov_33) for r in conds]
        out.update(cond_err_deg=float(np.degrees(np.median([np.linalg.norm(r.cond_err_3) for r in conds]))),
                   cond_sigma_deg=float(np.degrees(np.median([math.sqrt(np.trace(np.asarray(r.cond_cov_33)) / 3)
                                                              for r in conds]))),
                   cond_nees_median=float(np.median(cn)))
    if model:
        a, b = model['rotation']
        mn = [nees(r.rot_err_3, r.rot_cov_33, a, math.radians(b)) for r in rows]
        out.update(fit_rot_nees_median=float(np.median(mn)), fit_rot_beyond95=float(np.mean(np.asarray(mn) > CHI2_95[3])))
        if dirs:
            a, b = model['direction']
            mn = [nees(r.dir_err_2, r.dir_cov_22, a, math.radians(b)) for r in dirs]
            out.update(fit_dir_nees_median=float(np.median(mn)),
                       fit_dir_beyond95=float(np.mean(np.asarray(mn) > CHI2_95[2])))
    return out


def fit_blocks(rows: List[PairError]) -> Dict[str, Tuple[float, float]]:
    return {'rotation': fit_model([(r.rot_err_3, r.rot_cov_33) for r in rows]),
            'direction': fit_model([(r.dir_err_2, r.dir_cov_22) for r in rows if r.dir_err_2 is not None])}


def _fmt(s: Dict[str, float], key: str, spec: str = '.3f') -> str:
    v = s.get(key)
    return '' if v is None else format(v, spec)


def table(groups: Dict[str, List[PairError]], tried: Dict[str, int], model=None) -> str:
    head = ('| group | pairs (of tried) | rot err median / p90 (deg) | rot std said (deg) | rot NEES median | '
            'rot beyond 95 % | dir err (deg) | dir std said (deg) | dir NEES median | dir beyond 95 % | '
            'rot given dir: err / std said (deg), NEES'
            + (' | fitted: rot NEES / beyond 95 % | fitted: dir NEES / beyond 95 %' if model else '') + ' |')
    lines = [head, '|' + '---|' * (head.count('|') - 1)]
    for name, rows in groups.items():
        s = summary(rows, model)
        t = tried.get(name)
        cells = [name, f"{s['pairs']}" + (f' ({t})' if t else ''),
                 f"{_fmt(s, 'rot_err_deg')} / {_fmt(s, 'rot_err_p90_deg')}", _fmt(s, 'rot_sigma_deg', '.4f'),
                 _fmt(s, 'rot_nees_median', '.1f'), _fmt(s, 'rot_beyond95', '.0%'), _fmt(s, 'dir_err_deg', '.2f'),
                 _fmt(s, 'dir_sigma_deg', '.3f'), _fmt(s, 'dir_nees_median', '.1f'), _fmt(s, 'dir_beyond95', '.0%'),
                 f"{_fmt(s, 'cond_err_deg')} / {_fmt(s, 'cond_sigma_deg', '.4f')}, {_fmt(s, 'cond_nees_median', '.1f')}"]
        if model:
            cells += [f"{_fmt(s, 'fit_rot_nees_median', '.2f')} / {_fmt(s, 'fit_rot_beyond95', '.0%')}",
                      f"{_fmt(s, 'fit_dir_nees_median', '.2f')} / {_fmt(s, 'fit_dir_beyond95', '.0%')}"]
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
    """(name, images iterator factory, K, poses) of the data folder's sequences and the rendered seeds."""
    from dpv_sensor.benchmarks.stream_table import RENDER_SIZE, sequence_folders
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
    p.add_argument('--loso', action='store_true', help='also fit leaving each sequence out')
    p.add_argument('--json', type=pathlib.Path, help='write every pair and the fits here')
    a = p.parse_args(argv)
    from tqdm import tqdm
    size = (P.default('processing_width'), P.default('processing_height'))
    seeds = [int(s) for s in a.seeds.split(',') if s.strip()]
    config = dataclasses.replace(KeypointConfig(), rotation_floor_deg=0.0, direction_floor_deg=0.0)  # S_kp raw
    rows: Dict[str, List[PairError]] = {}
    tried: Dict[str, int] = {}
    for name, seq in _sequences(a.data, a.sequences, seeds, a.frames):
        poses = np.asarray(seq.poses, np.float64)
        kfs = keyframe_indices(poses)
        images = (seq.image(i) for i in tqdm(kfs, desc=name, unit='keyframe', leave=False))
        rows[name], tried[name] = sequence_pairs(name, images, seq.K, poses, size, a.sources, config)
    if not rows:
        p.error('no sequences: give --data or --seeds')
    every = [r for v in rows.values() for r in v]
    rendered = [r for r in every if is_rendered(r.sequence)]
    model = fit_blocks(rendered) if rendered else None
    print('## As the keypoint covariance says (S_kp)\n')
    print(table(rows, tried, model))
    if model:
        print(f"\nfitted on the rendered sequences ({len(rendered)} pairs): rotation a = {model['rotation'][0]:.3g}, "
              f"b = {model['rotation'][1]:.3g} deg; direction a = {model['direction'][0]:.3g}, "
              f"b = {model['direction'][1]:.3g} deg")
    print('\n## By inliers and parallax, rendered sequences\n')
    print(table(binned(rendered), {}, model))
    real = [r for r in every if not is_rendered(r.sequence)]
    if real:
        print('\n## By inliers and parallax, real sequences\n')
        print(table(binned(real), {}, model))
    loso = {}
    if a.loso:
        print('\n## Leave one sequence out (fit on all others, NEES on the one left out)\n')
        for name in rows:
            m = fit_blocks([r for r in every if r.sequence != name])
            loso[name] = {'model': m, 'summary': summary(rows[name], m)}
            s = loso[name]['summary']
            print(f"{name}: rotation a {m['rotation'][0]:.3g} b {m['rotation'][1]:.3g} deg, NEES "
                  f"{_fmt(s, 'fit_rot_nees_median', '.2f')} / beyond 95 % {_fmt(s, 'fit_rot_beyond95', '.0%')}; "
                  f"direction a {m['direction'][0]:.3g} b {m['direction'][1]:.3g} deg, NEES "
                  f"{_fmt(s, 'fit_dir_nees_median', '.2f')} / {_fmt(s, 'fit_dir_beyond95', '.0%')}")
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(to_jsonable({'pairs': [asdict(r) for r in every], 'tried': tried,
                                                  'model_rendered': model, 'loso': loso}), indent=1))
        print(f'\nwritten: {a.json}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
