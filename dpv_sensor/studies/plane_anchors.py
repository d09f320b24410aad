"""Texture-free depth judged by planes through the metric anchors around it: how much of it, and how accurately
(docs/adaptation.md, "Planes through the anchors").

    python -m dpv_sensor.studies.plane_anchors --data DATA --poses gt noisy0 [--every 10] [--out DIR]

The adapt tool's held-out judge scores depth at metric anchors: corners tracked and triangulated with the
recording's poses (:func:`dpv_sensor.training.anchor_judge.frame_anchors`). Corners lie on texture, and where the
networks' depth changes most under adaptation, the texture-free third of a frame, there are none. A blank wall,
floor or desk top is most often a plane bounded by texture: the anchors on its outline fix the plane, and the plane
gives the depth inside. This study measures that premise on the development folders before any judge uses it.

Per folder, at the adapt tool's processing size, every ``--every``-th frame is a reference; its anchors come from
the frames 2, 4, 8, 16, 32 away on each side with the pose source's poses (exactly the judge's). Its texture-free
pixels are the weakest third of local texture (:func:`dpv_sensor.studies.error_breakdown.local_texture`), split into
8-connected regions of at least ``--min-region`` pixels. A region's plane:

- **candidates**: the anchors on the region or within ``--band`` px of it, back-projected to 3-D in the reference;
- **fit**: RANSAC over triples, an anchor agreeing when its log depth is within ``max(0.03, 1.5 sigma_i)`` (capped
  at 0.1) of the plane's along its ray; the largest agreeing set, refitted by least squares (the smallest singular
  vector of the centred points), must hold at least ``--min-inliers`` anchors and ``--min-inlier-share`` of the
  candidates;
- **coverage**: the plane speaks only inside the convex hull of its agreeing anchors' pixels, on the region, and
  where it lies in front of the camera: no extrapolation past the outline that fixed it.

Printed per (folder, poses): references, texture-free pixels (with GT depth) covered by a plane, the planes'
error on them against the ground truth (median |log|, median signed log, share off by more than 10 %), and the
anchors' own error for comparison. The ground truth is read here only to score.
"""
from __future__ import annotations

import argparse
import json
import math
import pathlib
import sys
from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence as Seq

import cv2
import numpy as np
from scipy import ndimage

__all__ = ['PlaneConfig', 'Plane', 'texture_free_regions', 'fit_plane', 'plane_depth', 'region_planes', 'main']


@dataclass(frozen=True)
class PlaneConfig:
    """weak_share: the share of a frame's pixels (the least textured) that count as texture-free; min_region_px: a
    smaller connected texture-free region gets no plane; band_px: anchors this close to a region are its candidates;
    min_inliers / min_inlier_share: what a plane needs to be kept; tol_log / tol_sigmas / max_tol_log: an anchor
    agrees with a plane within max(tol_log, tol_sigmas * sigma_i), at most max_tol_log, in log depth; iterations:
    RANSAC triples tried (seeded); hull: the plane speaks only inside the hull of its anchors (False: on its whole
    region, an extrapolation)."""
    weak_share: float = 1.0 / 3.0
    min_region_px: int = 200
    band_px: int = 25
    min_inliers: int = 8
    min_inlier_share: float = 0.6
    tol_log: float = 0.03
    tol_sigmas: float = 1.5
    max_tol_log: float = 0.1
    iterations: int = 200
    hull: bool = True


@dataclass
class Plane:
    """n_3 . X = d in the reference camera's frame (|n| = 1, d > 0); inliers: the agreeing anchors' indices."""
    n_3: np.ndarray
    d: float
    inliers: np.ndarray


def texture_free_regions(image_hw3: np.ndarray, config: PlaneConfig = PlaneConfig()) -> tuple[np.ndarray, int]:
    """(labels_hw, count): the 8-connected regions of the frame's least textured ``weak_share`` of pixels with at
    least ``min_region_px`` pixels each, labelled 1..count (0: textured or too small)."""
    from dpv_sensor.studies.error_breakdown import local_texture
    tex = local_texture(image_hw3)
    weak = tex <= np.quantile(tex, config.weak_share)
    labels, n = ndimage.label(weak, structure=np.ones((3, 3), bool))
    sizes = np.bincount(labels.ravel(), minlength=n + 1)
    keep = sizes >= config.min_region_px
    keep[0] = False
    remap = np.zeros(n + 1, np.int64)
    remap[keep] = np.arange(1, int(keep.sum()) + 1)
    return remap[labels], int(keep.sum())


def _rays(uv_n2: np.ndarray, K_33: np.ndarray) -> np.ndarray:
    """K^-1 [u v 1]: the ray of each pixel, scaled to z = 1."""
    return np.c_[uv_n2, np.ones(len(uv_n2))] @ np.linalg.inv(K_33).T


def _plane_log_depth(n_3: np.ndarray, d: float, rays_n3: np.ndarray) -> np.ndarray:
    """log z where each ray (z = 1) meets the plane; NaN where it meets it behind the camera or not at all."""
    denom = rays_n3 @ n_3
    with np.errstate(divide='ignore', invalid='ignore'):
        z = d / denom
    return np.where(z > 0, np.log(np.where(z > 0, z, 1.0)), np.nan)


def _through(X_k3: np.ndarray) -> Optional[tuple[np.ndarray, float]]:
    """The least-squares plane through points (n, d) with d > 0, or None when they are (nearly) collinear or the
    plane passes through the camera centre."""
    c = X_k3.mean(axis=0)
    _, s, vt = np.linalg.svd(X_k3 - c)
    if len(X_k3) < 3 or s[1] < 1e-6 * max(s[0], 1e-12):
        return None
    n = vt[-1]
    d = float(n @ c)
    if abs(d) < 1e-6:
        return None
    return (n, d) if d > 0 else (-n, -d)


def fit_plane(uv_n2: np.ndarray, depth_n: np.ndarray, sigma_n: np.ndarray, K_33: np.ndarray,
              config: PlaneConfig = PlaneConfig(), seed: int = 0) -> Optional[Plane]:
    """The plane most anchors agree with (module doc), or None when none holds ``min_inliers`` and
    ``min_inlier_share`` of them."""
    n = len(depth_n)
    if n < max(3, config.min_inliers):
        return None
    rays = _rays(uv_n2, K_33)
    X = rays * depth_n[:, None]
    log_z = np.log(depth_n)
    tol = np.minimum(np.maximum(config.tol_log, config.tol_sigmas * sigma_n), config.max_tol_log)
    rng = np.random.default_rng(seed)
    best: Optional[np.ndarray] = None
    for _ in range(config.iterations):
        fit = _through(X[rng.choice(n, 3, replace=False)])
        if fit is None:
            continue
        agree = np.abs(_plane_log_depth(*fit, rays) - log_z) <= tol
        if best is None or agree.sum() > best.sum():
            best = agree
    if best is None or best.sum() < max(3, config.min_inliers):
        return None
    fit = _through(X[best])
    if fit is None:
        return None
    agree = np.abs(_plane_log_depth(*fit, rays) - log_z) <= tol
    if agree.sum() < config.min_inliers or agree.sum() < config.min_inlier_share * n:
        return None
    return Plane(fit[0], fit[1], np.flatnonzero(agree))


def plane_depth(plane: Plane, K_33: np.ndarray, mask_hw: np.ndarray) -> np.ndarray:
    """The plane's depth (m) at the pixels of ``mask_hw`` (NaN elsewhere and where the plane is behind)."""
    H, W = mask_hw.shape
    v, u = np.nonzero(mask_hw)
    out = np.full((H, W), np.nan)
    out[v, u] = np.exp(_plane_log_depth(plane.n_3, plane.d, _rays(np.c_[u, v].astype(np.float64), K_33)))
    return out


def region_planes(image_hw3: np.ndarray, anchors, config: PlaneConfig = PlaneConfig()) -> np.ndarray:
    """The depth the planes through ``anchors`` (a reference's :class:`~dpv_sensor.core.anchors.Anchors`) give on its
    texture-free regions, NaN where no plane speaks (module doc)."""
    labels, count = texture_free_regions(image_hw3, config)
    H, W = labels.shape
    out = np.full((H, W), np.nan)
    if count == 0 or len(anchors) == 0:
        return out
    uv = np.asarray(anchors.uv_n2, np.float64)
    px = np.clip(np.round(uv).astype(np.int64), 0, [W - 1, H - 1])
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * config.band_px + 1, 2 * config.band_px + 1))
    for r in range(1, count + 1):
        region = labels == r
        near = cv2.dilate(region.astype(np.uint8), kernel) > 0
        cand = np.flatnonzero(near[px[:, 1], px[:, 0]])
        plane = fit_plane(uv[cand], anchors.depth_n[cand], anchors.sigma_n[cand], anchors.K_33, config, seed=r)
        if plane is None:
            continue
        hull = np.zeros((H, W), np.uint8)
        pts = uv[cand[plane.inliers]].astype(np.float32)
        cv2.fillConvexPoly(hull, cv2.convexHull(pts).astype(np.int32).reshape(-1, 2), 1)
        covered = region & (hull > 0) if config.hull else region
        z = plane_depth(plane, anchors.K_33, covered)
        out[covered] = z[covered]
    return out


def _score(seq, refs: Seq[int], anchors: Dict, config: PlaneConfig) -> Dict:
    """Coverage and accuracy of the planes and of the anchors against the ground truth."""
    from dpv_sensor.core.anchors import sample_depth
    plane_err, anchor_err, covered_px, weak_px = [], [], 0, 0
    for k in refs:
        gt = np.asarray(seq.depth(k), np.float64)
        a = anchors[k]
        if len(a):
            g = sample_depth(gt, a.uv_n2)
            ok = np.isfinite(g) & (g > 0)
            anchor_err.append(np.log(a.depth_n[ok]) - np.log(g[ok]))
        labels, _ = texture_free_regions(seq.image(k), config)
        weak = (labels > 0) & (gt > 0)
        weak_px += int(weak.sum())
        z = region_planes(seq.image(k), a, config)
        cov = weak & np.isfinite(z)
        covered_px += int(cov.sum())
        plane_err.append(np.log(z[cov]) - np.log(gt[cov]))
    pe = np.concatenate(plane_err) if plane_err else np.zeros(0)
    ae = np.concatenate(anchor_err) if anchor_err else np.zeros(0)

    def stats(e: np.ndarray) -> Dict:
        if e.size == 0:
            return {'n': 0}
        return {'n': int(e.size), 'median_abs_log': float(np.median(np.abs(e))),
                'median_log': float(np.median(e)), 'share_over_10pct': float(np.mean(np.abs(e) > math.log(1.1)))}
    return {'references': len(refs), 'texture_free_px': weak_px,
            'covered_share': covered_px / weak_px if weak_px else 0.0, 'planes': stats(pe), 'anchors': stats(ae)}


def study(folder: pathlib.Path, pose_source: str, every: int, width: int, height: int,
          config: PlaneConfig = PlaneConfig()) -> Dict:
    from dpv_sensor.benchmarks.stream_table_inputs import odometry_poses
    from dpv_sensor.data.sequence import Sequence
    from dpv_sensor.training.anchor_judge import frame_anchors
    seq = Sequence(folder).resized(width, height).materialize()
    seq = seq.with_poses(odometry_poses(seq, pose_source))
    refs = list(range(every // 2, len(seq), every))
    anchors = frame_anchors(seq, refs, lambda i: True)
    return _score(seq, refs, anchors, config)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog='python -m dpv_sensor.studies.plane_anchors', description=__doc__.split('\n')[0])
    ap.add_argument('--data', required=True, type=pathlib.Path, help='a folder of sequence folders')
    ap.add_argument('--sequences', nargs='*', default=None, help='which of them (default: all)')
    ap.add_argument('--poses', nargs='+', default=['gt', 'noisy0'], help="pose sources ('gt', 'noisy<seed>', ...)")
    ap.add_argument('--every', type=int, default=10, help='every this many frames is a reference')
    ap.add_argument('--width', type=int, default=320)
    ap.add_argument('--height', type=int, default=256)
    ap.add_argument('--min-region', type=int, default=PlaneConfig.min_region_px)
    ap.add_argument('--band', type=int, default=PlaneConfig.band_px)
    ap.add_argument('--min-inliers', type=int, default=PlaneConfig.min_inliers)
    ap.add_argument('--no-hull', action='store_true', help='let a plane speak on its whole region')
    ap.add_argument('--out', type=pathlib.Path, default=None, help='write plane_anchors.json here')
    a = ap.parse_args(argv)
    config = PlaneConfig(min_region_px=a.min_region, band_px=a.band, min_inliers=a.min_inliers, hull=not a.no_hull)
    names = a.sequences or sorted(p.name for p in a.data.iterdir() if (p / 'poses.txt').is_file())
    rows: List[Dict] = []
    print('| folder | poses | references | texture-free px covered | planes: median abs err, signed, > 10 % '
          '| anchors: n, median abs err, signed, > 10 % |')
    print('|---|---|---|---|---|---|')
    for name in names:
        for source in a.poses:
            r = study(a.data / name, source, a.every, a.width, a.height, config)
            r.update(folder=name, poses=source)
            rows.append(r)
            p, an = r['planes'], r['anchors']

            def fmt(s):
                if not s['n']:
                    return '–'
                return (f"{100 * (math.exp(s['median_abs_log']) - 1):.1f} %, {100 * s['median_log']:+.1f} %, "
                        f"{100 * s['share_over_10pct']:.0f} %")
            print(f"| {name} | {source} | {r['references']} | {100 * r['covered_share']:.0f} % | {fmt(p)} | "
                  f"{an['n']}, {fmt(an)} |", flush=True)
    if a.out:
        a.out.mkdir(parents=True, exist_ok=True)
        (a.out / 'plane_anchors.json').write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == '__main__':
    sys.exit(main())
