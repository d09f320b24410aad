"""How well a window's baselines constrain depth: per-pixel parallax, and source choice by it.

Depth is observable only through parallax: a point seen from two camera centres moves in the image as
its depth changes, and by nothing when the cameras share a centre (a pure rotation). :func:`disparity_span`
measures, per reference pixel and depth estimate ``d``, how many pixels the point's image in a source view
moves while its depth runs over the band ``[d / ratio, d * ratio]`` (by default ``BAND_RATIO`` = 1.25, the
band of the delta < 1.25 measure), and takes the largest over the sources that see the point. A span well below
a pixel means that no matching cost can tell ``d`` from ``d * ratio``: the measurement says nothing about
depth there, however peaked the network's DPV is.

:func:`parallax_support` turns a span into a weight in [0, 1] (linear up to ``full_px``), used by the
estimator to weight the filter update per pixel and to shape the published confidence.

:func:`select_sources` picks the source keyframes of a window from a pool of recent keyframes by how well
their baselines constrain the reference's depth (a pose-distance score in the spirit of DeepVideoMVS's
keyframe selection): the median disparity span of the reference's pixels at a nominal depth, counting only
pixels the source sees (overlap), so a large baseline that looks elsewhere scores low.

torch and numpy only; no ROS.
"""
from __future__ import annotations

from typing import List, Sequence

import numpy as np
import torch

from dpv_sensor.core.geometry import Z_EPS, backproject, project, rotation_angle, transform_points
from dpv_sensor.core.pose_math import scale_intrinsics_np

__all__ = ['disparity_span', 'parallax_support', 'pose_parallax_score', 'select_sources', 'BAND_RATIO',
           'rotation_noise_px']

# The depth band whose disparity is measured: [d / BAND_RATIO, d * BAND_RATIO], the delta < 1.25 band (fixed,
# so that the depth does not depend on how the confidence is defined).
BAND_RATIO = 1.25


def disparity_span(depth_bhw: torch.Tensor, K_b33: torch.Tensor, T_src_ref_bn44: torch.Tensor,
                   ratio: float = BAND_RATIO, src_hw=None, per_source: bool = False) -> torch.Tensor:
    """(B, H, W) pixels: the largest, over the N sources, image displacement in a source between the
    points at depth ``d / ratio`` and ``d * ratio`` on each reference pixel's ray (``d`` = ``depth_bhw``).

    ``K_b33`` describes both the reference grid (H x W) and the sources' (same camera); the span is in
    pixels of that grid. A source contributes only where the point at ``d`` lies in front of it and, when
    ``src_hw`` = (h, w) is given, inside its image; both band ends must be in front of it. Pixels without
    a finite positive depth get 0. ``per_source``: return every source's span, (N, B, H, W), instead of the
    largest.
    """
    B, H, W = depth_bhw.shape
    dt = torch.float32
    T = T_src_ref_bn44.to(dt)
    if T.dim() == 3:
        T = T[None]
    N = T.shape[1]
    if N == 0:
        return torch.zeros((0, B, H, W) if per_source else (B, H, W), dtype=dt, device=depth_bhw.device)
    K = K_b33.to(dt).expand(B, 3, 3)
    ok = torch.isfinite(depth_bhw) & (depth_bhw > 0)
    d = torch.where(ok, depth_bhw.to(dt), torch.ones_like(depth_bhw, dtype=dt))
    r = float(ratio)
    # every source and both band ends and the depth itself in one batch: (N, 3, B) rays of H*W points
    d_sb = torch.stack([d * (1.0 / r), d * r, d])                                       # 3, B, H, W
    pts = backproject(d_sb.reshape(3 * B, H, W), K.repeat(3, 1, 1)).reshape(1, 3 * B, 3, H * W)
    T_n = T.transpose(0, 1)[:, None].expand(N, 3, B, 4, 4).reshape(N, 3 * B, 4, 4)
    p, z = project(transform_points(T_n, pts.expand(N, 3 * B, 3, H * W)).reshape(N * 3 * B, 3, H * W),
                   K.repeat(3 * N, 1, 1))
    uv = p.reshape(N, 3, B, 2, H * W)
    front = ok.reshape(1, B, H * W) & (z.reshape(N, 3, B, H * W) > Z_EPS).all(1)          # N, B, HW
    span = (uv[:, 1] - uv[:, 0]).norm(dim=2)                                           # N, B, HW
    if src_hw is not None:
        h, w = int(src_hw[0]), int(src_hw[1])
        u, v = uv[:, 2, :, 0], uv[:, 2, :, 1]
        front = front & (u >= -0.5) & (u <= w - 0.5) & (v >= -0.5) & (v <= h - 0.5)
    spans = torch.where(front, span, torch.zeros_like(span)).reshape(N, B, H, W)
    return spans if per_source else spans.amax(0)


def rotation_noise_px(T_src_ref_bn44: torch.Tensor, f_px: float, fraction: float) -> torch.Tensor:
    """(B, N) pixels: ``fraction`` of the image motion a source's rotation relative to the reference causes
    (``f_px * angle``). Pose errors of real cameras grow with the rotation between two views (time-sync
    offsets, rolling shutter, motion blur all scale with it), and a disparity below them tells nothing."""
    T = T_src_ref_bn44.to(torch.float32)
    if T.dim() == 3:
        T = T[None]
    return float(fraction) * float(f_px) * rotation_angle(T[..., :3, :3])


def parallax_support(span_bhw: torch.Tensor, full_px: float) -> torch.Tensor:
    """Weight in [0, 1] of a disparity span: ``span / full_px`` clamped to [0, 1] (1 everywhere when
    ``full_px`` <= 0, i.e. the parallax rule is off)."""
    if full_px <= 0:
        return torch.ones_like(span_bhw)
    return (span_bhw / float(full_px)).clamp(0.0, 1.0)


def pose_parallax_score(T_world_ref_44: np.ndarray, T_world_src_44: np.ndarray, K_33: np.ndarray,
                        hw, depth: float, ratio: float = BAND_RATIO, step: int = 8) -> float:
    """How well one source constrains the reference's depth, in pixels: the median, over a grid of the
    reference's pixels (every ``step`` pixels) assumed at depth ``depth``, of the disparity span
    (:func:`disparity_span`), pixels the source does not see counting as 0 (so the score falls with the
    overlap as well as with a short baseline). Numpy poses ``T_world_cam``; K and hw describe the images."""
    h, w = int(hw[0]), int(hw[1])
    K = np.asarray(K_33, dtype=np.float64)
    # a coarse grid with the intrinsics of every step-th pixel
    hs, ws = max(1, h // step), max(1, w // step)
    Kc = scale_intrinsics_np(K, ws / w, hs / h)
    T_src_ref = np.linalg.inv(np.asarray(T_world_src_44, dtype=np.float64)) @ np.asarray(T_world_ref_44,
                                                                                           dtype=np.float64)
    Kt = torch.as_tensor(Kc, dtype=torch.float32)[None]
    Tt = torch.as_tensor(T_src_ref, dtype=torch.float32)[None, None]
    d = torch.full((1, hs, ws), float(depth))
    span = disparity_span(d, Kt, Tt, ratio, src_hw=(hs, ws))
    return float(span.median()) * (w / ws)


def select_sources(ref_index: int, candidates: Sequence[int], scores: Sequence[float], count: int,
                   min_score: float) -> List[int]:
    """Indices (into the pool) of the sources for a reference: among ``candidates`` (pool indices, in time
    order) the ``count`` with the highest ``scores`` (pixels, :func:`pose_parallax_score`), preferring,
    among those that reach ``min_score``, the ones closest in time to the reference (less appearance change,
    more overlap), and filling up with the best-scoring rest. Returned in time order."""
    cand = [c for c in candidates if c != ref_index]
    if len(cand) <= count:
        return sorted(cand)
    good = [c for c, s in zip(candidates, scores) if c != ref_index and s >= min_score]
    good.sort(key=lambda c: (abs(c - ref_index), c))
    chosen = good[:count]
    if len(chosen) < count:
        rest = sorted(((s, c) for c, s in zip(candidates, scores) if c != ref_index and c not in chosen),
                      key=lambda sc: (-sc[0], abs(sc[1] - ref_index)))
        chosen += [c for _, c in rest[:count - len(chosen)]]
    return sorted(chosen)
