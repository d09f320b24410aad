"""How much the photometric alignment's rotation depends on the quality of the reference depth it is given.

    .venv/bin/python -m dpv_sensor.studies.alignment_depth SEQUENCE [--size 320x256] [--gap 5] [--pairs 20]
        [--error 0.3]

Pairs of frames ``gap`` apart of a sequence folder (every 10th frame as reference) are aligned
(``core.photometric.align_photometric`` with the window refiner's alignment settings) from the GT relative pose
perturbed by 0.2 deg per axis and 2 mm (the same perturbations for every depth), against three reference depths:
the GT depth, the GT depth at a quarter of the size scaled by a random 10 % (smooth, biased), and the GT depth times
``exp(error * f)`` with ``f`` a smooth random field scaled to unit std (structured errors of the size a plane sweep
leaves: ``--error 0.3`` is about abs_rel 0.25). Prints the median rotation error of the converged alignments
against the GT relative pose.
"""
from __future__ import annotations

import argparse
import sys
from typing import List, Optional

import numpy as np

DEPTHS = ('gt', 'smooth', 'structured')


def perturbed_depth(d: np.ndarray, mode: str, error: float, rng: np.random.Generator) -> np.ndarray:
    """The reference depth an alignment is given (module doc)."""
    import cv2
    h, w = d.shape
    if mode == 'gt':
        return d
    if mode == 'smooth':
        small = cv2.resize(d, (w // 4, h // 4), interpolation=cv2.INTER_NEAREST)
        return cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR) * float(1.0 + 0.1 * rng.standard_normal())
    field = cv2.resize(rng.standard_normal((4, 5)).astype(np.float32), (w, h), interpolation=cv2.INTER_CUBIC)
    return d * np.exp(error * field / max(float(field.std()), 1e-6))


def main(argv: Optional[List[str]] = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0], epilog=__doc__.split('\n\n', 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('sequence')
    p.add_argument('--size', default='320x256', help='WxH the images and depth are resized to')
    p.add_argument('--gap', type=int, default=5, help='frames between the two views')
    p.add_argument('--pairs', type=int, default=20)
    p.add_argument('--error', type=float, default=0.3, help='std of the structured log-depth error')
    p.add_argument('--threads', type=int, default=2)
    p.add_argument('--finest-level', type=int, default=None, help="the alignment's finest pyramid level "
                   "(default: the refiner's)")
    p.add_argument('--max-pixels', type=int, default=None, help="pixels per level (default: the refiner's)")
    p.add_argument('--step-tolerance', type=float, default=None, help="the alignment's convergence step "
                   "(default: the refiner's)")
    a = p.parse_args(argv)
    import cv2
    import torch
    from scipy.spatial.transform import Rotation
    from dpv_sensor.core.photometric import align_photometric
    from dpv_sensor.data.sequence import Sequence
    from dpv_sensor.stream.window_refiner import PoseRefinerConfig
    torch.set_num_threads(a.threads)
    config = PoseRefinerConfig().alignment
    if a.finest_level is not None:
        config.finest_level = a.finest_level
    if a.max_pixels is not None:
        config.max_pixels = a.max_pixels
    if a.step_tolerance is not None:
        config.step_tolerance = a.step_tolerance
    w, h = (int(v) for v in a.size.lower().split('x'))
    seq = Sequence(a.sequence)
    H0, W0 = seq.image(0).shape[:2]
    K = np.asarray(seq.K, np.float64).copy()
    K[0] *= w / W0
    K[1] *= h / H0
    starts = list(range(0, len(seq) - a.gap, 10))[:a.pairs]
    for mode in DEPTHS:
        rng = np.random.default_rng(0)               # the depth errors
        pose_rng = np.random.default_rng(1)          # the starting poses: the same for every depth
        errors = []
        for i in starts:
            grey = [torch.from_numpy(cv2.cvtColor(cv2.resize(seq.image(j), (w, h), interpolation=cv2.INTER_AREA),
                                                  cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0)
                    for j in (i, i + a.gap)]
            d = cv2.resize(np.asarray(seq.depth(i), np.float32), (w, h), interpolation=cv2.INTER_NEAREST)
            d = perturbed_depth(d, mode, a.error, rng)
            T_gt = np.linalg.inv(np.asarray(seq.pose(i + a.gap))) @ np.asarray(seq.pose(i))     # T_src_ref
            P = np.eye(4)
            P[:3, :3] = Rotation.from_rotvec(pose_rng.normal(0.0, np.radians(0.2), 3)).as_matrix()
            P[:3, 3] = pose_rng.normal(0.0, 0.002, 3)
            res = align_photometric(grey[0], grey[1], torch.from_numpy(d.astype(np.float32)), K, P @ T_gt,
                                    config=config)
            if res.converged:
                D = res.T_src_ref_44 @ np.linalg.inv(T_gt)
                errors.append(np.degrees(np.linalg.norm(Rotation.from_matrix(D[:3, :3]).as_rotvec())))
        med = float(np.median(errors)) if errors else float('nan')
        print(f'{a.sequence} {w}x{h} gap {a.gap}, depth {mode}: median rotation error {med:.3f} deg '
              f'({len(errors)}/{len(starts)} converged)', flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
