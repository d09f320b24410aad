"""Tiny analytic scenes for the core tests (no interpolation anywhere in the rendering).

- :func:`texture`: a smooth, aperiodic-looking 2-D pattern (sum of sinusoids) in [0, 1].
- :func:`render_plane_pair`: a textured fronto-parallel plane at depth z seen by a reference and a
  source camera; the source image is rendered through the plane-induced homography
  ``x_ref ~ K_ref (R + t n^T / z)^-1 K_src^-1 x_src`` (texture defined on reference pixels).
- :func:`render_scene`: ray-casting of axis-aligned, textured fronto-parallel rectangles (world z =
  const) into any camera: exact image and z-depth, so occlusions and disocclusions are exact.
Helpers use float64 torch tensors.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence, Tuple

import torch

DT = torch.float64

# (wavelength, angle, phase, amplitude): wavelengths in texture units.
_WAVES = [(5.3, 0.3, 0.1, 0.22), (7.9, 1.4, 1.7, 0.2), (11.7, 2.5, 0.6, 0.18),
          (6.1, 3.9, 2.9, 0.15), (17.3, 5.1, 1.1, 0.15), (9.2, 0.9, 4.0, 0.1)]


def texture(x: torch.Tensor, y: torch.Tensor, scale: float = 1.0, seed: int = 0) -> torch.Tensor:
    """Pattern in [0, 1] at coordinates (x, y) / scale; ``seed`` rotates/shifts the waves."""
    out = torch.full_like(x, 0.5)
    for i, (lam, ang, ph, amp) in enumerate(_WAVES):
        a = ang + 0.77 * seed
        p = ph + 1.3 * seed * (i + 1)
        k = 2 * math.pi / (lam * scale)
        out = out + amp * torch.sin(k * (math.cos(a) * x + math.sin(a) * y) + p) * 0.5
    return out.clamp(0.0, 1.0)


def intrinsics(w: int, h: int, f: float) -> torch.Tensor:
    """Pinhole K (1x3x3) with the principal point at the image centre."""
    return torch.tensor([[[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]]], dtype=DT)


def rot_x(a):
    c, s = math.cos(a), math.sin(a)
    return torch.tensor([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=DT)


def rot_y(a):
    c, s = math.cos(a), math.sin(a)
    return torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=DT)


def rot_z(a):
    c, s = math.cos(a), math.sin(a)
    return torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=DT)


def se3(R=None, t=(0.0, 0.0, 0.0)) -> torch.Tensor:
    """A 1x4x4 transform."""
    T = torch.eye(4, dtype=DT)
    if R is not None:
        T[:3, :3] = R
    T[:3, 3] = torch.as_tensor(t, dtype=DT)
    return T[None]


def _pixels(h, w):
    v, u = torch.meshgrid(torch.arange(h, dtype=DT), torch.arange(w, dtype=DT), indexing='ij')
    return u, v


def render_plane_pair(K_ref, K_src, T_src_ref, z: float, h: int, w: int, tex_scale: float = 1.0
                      ) -> Tuple[torch.Tensor, torch.Tensor]:
    """Reference and source images (1x1xHxW) of the plane Z_ref = z textured in reference pixels.

    Source pixels are mapped to reference pixels by the inverse of the plane-induced homography
    ``H_src_ref = K_src (R + t n^T / z) K_ref^-1`` with n = (0, 0, 1).
    """
    n = torch.tensor([[0.0, 0.0, 1.0]], dtype=DT)
    R, t = T_src_ref[0, :3, :3], T_src_ref[0, :3, 3:]
    Hm = K_src[0] @ (R + t @ n / z) @ torch.linalg.inv(K_ref[0])
    Hinv = torch.linalg.inv(Hm)
    u, v = _pixels(h, w)
    ref = texture(u, v, tex_scale)
    x = torch.stack([u.reshape(-1), v.reshape(-1), torch.ones(h * w, dtype=DT)])
    xr = Hinv @ x
    ur, vr = (xr[0] / xr[2]).reshape(h, w), (xr[1] / xr[2]).reshape(h, w)
    src = texture(ur, vr, tex_scale)
    return ref[None, None], src[None, None]


@dataclass
class Rect:
    """Fronto-parallel rectangle at world z = ``z`` spanning [x0, x1] x [y0, y1] (metres)."""
    z: float
    x0: float = -1e9
    x1: float = 1e9
    y0: float = -1e9
    y1: float = 1e9
    seed: int = 0
    tex_scale: float = 0.04  # metres per texture unit


def render_scene(rects: Sequence[Rect], K: torch.Tensor, T_world_cam: torch.Tensor, h: int, w: int
                 ) -> Tuple[torch.Tensor, torch.Tensor]:
    """Grey image (1x1xHxW) and z-depth (1xHxW, 0 where nothing is hit) by exact ray casting."""
    u, v = _pixels(h, w)
    x = torch.stack([u.reshape(-1), v.reshape(-1), torch.ones(h * w, dtype=DT)])
    rays_c = torch.linalg.inv(K[0]) @ x                        # camera-frame rays with z = 1
    R, t = T_world_cam[0, :3, :3], T_world_cam[0, :3, 3]
    rays_w = R @ rays_c
    best_s = torch.full((h * w,), float('inf'), dtype=DT)
    img = torch.zeros(h * w, dtype=DT)
    for r in rects:
        s = (r.z - t[2]) / rays_w[2]                            # ray parameter = camera z-depth
        P = t[:, None] + s * rays_w
        hit = (s > 1e-6) & (P[0] >= r.x0) & (P[0] <= r.x1) & (P[1] >= r.y0) & (P[1] <= r.y1) & (s < best_s)
        val = texture(P[0] / r.tex_scale, P[1] / r.tex_scale, 1.0, r.seed)
        img = torch.where(hit, val, img)
        best_s = torch.where(hit, s, best_s)
    depth = torch.where(torch.isfinite(best_s), best_s, torch.zeros_like(best_s))
    return img.reshape(1, 1, h, w), depth.reshape(1, h, w)
