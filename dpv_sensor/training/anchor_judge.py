"""Metric anchors of a recording's keyframes for adaptation: the held-out judge of depth, and a sparse depth loss.

A photometric score cannot see depth where the images have no texture, and it approved adapted weights whose depth
was worse. Anchors measure the depth itself: the corners of a keyframe are tracked into the frames 2, 4, 8, 16, 32
away on each side (pyramidal Lucas-Kanade started where the poses' rotation alone would put them, checked by
tracking back) and triangulated with the recording's metric poses (:mod:`dpv_sensor.core.anchors`: in front of both
cameras, with parallax, within the reprojection bound, a σ of log depth each, a pose error assumed in every pair).
They use no network, so the base and the adapted weights are judged on the very same points. The frames they may
come from are the caller's choice: a held-out keyframe's anchors come from frames never trained on (anything but a
training keyframe: the frames between keyframes are never trained on either, and a held-out block alone is too
short for parallax), a training keyframe's from frames outside the held-out parts.

- :class:`AnchorScore`: the held-out judge's score of one run: the σ-weighted mean absolute error in log depth of
  the depth at the anchors' pixels, ``sum_i w_i |log z_i - log d(u_i)| / sum_i w_i`` with ``w_i = 1 / s_i^2`` and
  ``s_i^2 = sigma_i^2 + depth_sigma_log^2`` (the depth map's own error, so a few very precise anchors do not
  outvote the rest); absolute, not squared, so a few wrong matches move it little. NaN with fewer than
  ``min_anchors`` anchors (the run cannot be judged).
- :func:`anchor_loss`: the same residuals on a training keyframe's depth as a differentiable loss, each divided by
  its ``s_i`` and put through a Huber function at ``huber_k`` (a sparse, metric pull on the depth's scale where
  the photometry cannot tell it).

numpy, OpenCV and torch; no ROS.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Callable, Dict, Optional, Sequence as Seq

import cv2
import numpy as np
import torch

from dpv_sensor.core import anchors as anchor_math
from dpv_sensor.core.anchors import AnchorConfig, Anchors

__all__ = ['JUDGES', 'JudgeConfig', 'frame_anchors', 'AnchorScore', 'anchor_loss', 'anchor_residuals']

#: what decides whether adapted weights are written: the anchors' depth error (the photometric score beside it may
#: veto), or the photometric score alone
JUDGES = ('anchors', 'photometric')


@dataclasses.dataclass(frozen=True)
class JudgeConfig:
    """offsets: the frames (this many away on each side) a keyframe's corners are tracked into; pose_sigma_deg: the
    rotation error assumed in every relative pose (rays that meet at too small an angle for it are not used); corners:
    at most this many
    corners a keyframe (Shi-Tomasi, ``corner_quality`` of the strongest, ``corner_spacing_px`` apart); anchors: the
    triangulation's and tracker's settings (the tracker with a wider window and more pyramid levels than the node's,
    which starts from the flow's guess: here the guess is the rotation's alone); min_anchors: a held-out run with
    fewer anchors over its references is not judged; huber_k: the loss's Huber threshold in σ."""
    offsets: tuple = (2, 4, 8, 16, 32)
    pose_sigma_deg: float = 0.3
    corners: int = 400
    corner_quality: float = 0.01
    corner_spacing_px: float = 5.0
    anchors: AnchorConfig = AnchorConfig(track_window_px=15, track_levels=3, min_anchors=1)
    min_anchors: int = 20
    huber_k: float = 1.5


def _gray(rgb: np.ndarray) -> np.ndarray:
    img = np.asarray(rgb)
    if img.dtype != np.uint8:
        img = np.clip(np.asarray(img, np.float64) * (255.0 if img.max() <= 1.0 else 1.0), 0, 255).astype(np.uint8)
    return cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img


def _rotation_guess(p_n2: np.ndarray, K_33: np.ndarray, R_src_ref: np.ndarray) -> np.ndarray:
    """Where the pixels would be in the source if the camera had only turned (the homography at infinity)."""
    x = np.c_[p_n2, np.ones(len(p_n2))] @ (K_33 @ R_src_ref @ np.linalg.inv(K_33)).T
    with np.errstate(divide='ignore', invalid='ignore'):
        q = x[:, :2] / x[:, 2:3]
    q[~(x[:, 2] > 0)] = np.nan
    return q


def frame_anchors(seq, refs: Seq[int], allowed: Callable[[int], bool], config: JudgeConfig = JudgeConfig()
                  ) -> Dict[int, Anchors]:
    """The anchors of every frame of ``refs`` (frame indices of ``seq``: ``image(i)``, ``pose(i)`` (T_world_cam,
    metres), ``K`` at the images' size and ``len``), each from the frames ``offsets`` away on each side (or the one
    next to it) for which ``allowed`` is true (module doc); an empty set where none is made."""
    K = np.asarray(seq.K, np.float64)
    n = len(seq)
    gray: Dict[int, np.ndarray] = {}

    def image(i: int) -> np.ndarray:
        if i not in gray:
            gray[i] = _gray(seq.image(i))
        return gray[i]

    out: Dict[int, Anchors] = {}
    for k in (int(r) for r in refs):
        sources = []
        for o in config.offsets:
            for sign in (1, -1):
                f = next((c for c in (k + sign * o, k + sign * (o + 1), k + sign * (o - 1))
                          if 0 <= c < n and c != k and allowed(c) and c not in sources), None)
                if f is not None:
                    sources.append(f)
        corners = cv2.goodFeaturesToTrack(image(k), config.corners, config.corner_quality, config.corner_spacing_px) \
            if sources else None
        if corners is None:
            out[k] = Anchors.empty(K)
            continue
        p_ref = corners.reshape(-1, 2).astype(np.float64)
        parts = []
        for j, s in enumerate(sources):
            T_src_ref = np.linalg.inv(np.asarray(seq.pose(s), np.float64)) @ np.asarray(seq.pose(k), np.float64)
            guess = _rotation_guess(p_ref, K, T_src_ref[:3, :3])
            p_src = anchor_math.refine_tracks(image(k), p_ref, image(s), guess, config.anchors)
            seen = np.all(np.isfinite(p_src), axis=1)
            if seen.sum() < 2:
                continue
            parts.append(anchor_math.triangulate_pair(p_ref[seen], p_src[seen], K, T_src_ref,
                                                      sigma_rot_rad=math.radians(config.pose_sigma_deg), pair=j,
                                                      config=config.anchors))
        out[k] = anchor_math.concat_anchors(parts) if parts else Anchors.empty(K)
    return out


def anchor_residuals(depth_hw: np.ndarray, anchors: Anchors, depth_sigma_log: float
                     ) -> tuple[np.ndarray, np.ndarray]:
    """(log z_anchor - log depth at its pixel, s_i) of the anchors where the depth map has depth."""
    if len(anchors) == 0:
        return np.zeros(0), np.zeros(0)
    d = anchor_math.sample_depth(depth_hw, anchors.uv_n2)
    ok = np.isfinite(d) & (d > 0)
    r = np.log(anchors.depth_n[ok]) - np.log(d[ok])
    s = np.sqrt(anchors.sigma_n[ok] ** 2 + depth_sigma_log ** 2)
    return r, s


class AnchorScore:
    """The held-out judge's score of one run (module doc), accumulated over its references' depth maps."""

    def __init__(self, config: JudgeConfig = JudgeConfig()):
        self.config = config
        self.num = 0.0
        self.den = 0.0
        self.count = 0

    def add(self, depth_hw: np.ndarray, anchors: Optional[Anchors]) -> None:
        if anchors is None or len(anchors) == 0:
            return
        r, s = anchor_residuals(depth_hw, anchors, self.config.anchors.depth_sigma_log)
        w = 1.0 / s ** 2
        self.num += float(np.sum(w * np.abs(r)))
        self.den += float(np.sum(w))
        self.count += int(r.size)

    @property
    def value(self) -> float:
        return self.num / self.den if self.count >= self.config.min_anchors and self.den > 0 else math.nan


def anchor_loss(depth_bhw: torch.Tensor, anchors_b: Seq[Optional[Anchors]], config: JudgeConfig = JudgeConfig()
                ) -> Optional[torch.Tensor]:
    """The mean Huber loss of the σ-normalised log-depth residuals of every anchor of every batch element's depth
    map (bilinear at the anchors' pixels, differentiable in the depth); None when the batch has no anchor."""
    B, H, W = depth_bhw.shape
    losses = []
    k = config.huber_k
    for b, a in enumerate(anchors_b):
        if a is None or len(a) == 0:
            continue
        uv = torch.as_tensor(a.uv_n2, dtype=depth_bhw.dtype)
        grid = torch.stack([uv[:, 0] / max(W - 1, 1) * 2 - 1, uv[:, 1] / max(H - 1, 1) * 2 - 1], -1)
        d = torch.nn.functional.grid_sample(depth_bhw[b][None, None], grid[None, None], mode='bilinear',
                                            align_corners=True)[0, 0, 0]
        s = torch.as_tensor(np.sqrt(a.sigma_n ** 2 + config.anchors.depth_sigma_log ** 2), dtype=depth_bhw.dtype)
        z = torch.as_tensor(a.depth_n, dtype=depth_bhw.dtype)
        ok = d > 0
        if not bool(ok.any()):
            continue
        x = (torch.log(z[ok]) - torch.log(d[ok])) / s[ok]
        ax = x.abs()
        losses.append(torch.where(ax <= k, 0.5 * x ** 2, k * (ax - 0.5 * k)))
    if not losses:
        return None
    return torch.cat(losses).mean()
