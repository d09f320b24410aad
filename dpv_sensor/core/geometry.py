"""Camera geometry for dpv_sensor: pinhole cameras, SE(3), back-projection and the warps.

Everything here is torch, batched, differentiable and dtype/device agnostic (float32 by default,
float64 for gradchecks, CPU or CUDA alike). No ROS import, no numpy in the hot paths. The same maths on single
float64 numpy poses and intrinsics (quaternions, interpolation, resized intrinsics) is in
:mod:`dpv_sensor.core.pose_math`.

Conventions:
- OpenCV camera axes (x right, y down, z forward); z-depth in metres.
- ``T_a_b`` (4x4, batched ``..._b44``) maps points in frame b to frame a: ``X_a = R X_b + t``.
- Pixel centres at integer coordinates; ``grid_sample`` with ``align_corners=True`` on
  coordinates normalised as ``2*u/(W-1) - 1``.
- Scaling an image by s changes K as ``fx' = fx*s``, ``cx' = (cx + 0.5)*s - 0.5`` (same for y).
- Depth planes are uniform in inverse depth, index 0 = d_min (nearest), index D-1 = d_max.
- K and T arguments with batch size 1 broadcast over the batch of the image / volume.
"""
from __future__ import annotations

import functools
from typing import Optional, Sequence, Tuple

import numpy as np
import torch
import torch.nn.functional as F

# Points closer than this to the camera plane (metres) are treated as not visible.
Z_EPS = 1e-6
# Tolerance (pixels / plane indices) when deciding whether a sample lies inside an image or volume.
BOUNDS_TOL = 1e-3

__all__ = [
    'scale_intrinsics', 'subsampled_intrinsics', 'invert_se3', 'make_se3', 'so3_exp', 'se3_exp', 'rotation_angle',
    'pixel_grid', 'backproject', 'project', 'transform_points',
    'camera_grid_affine', 'camera_resample_grid', 'resample_to_camera',
    'plane_sweep_warp', 'warp_volume', 'warp_image_with_depth', 'inverse_depth_index', 'inverse_depth_step',
]


# ----------------------------------------------------------------------------------------------
# Intrinsics
# ----------------------------------------------------------------------------------------------


def subsampled_intrinsics(K_33, stride: int):
    """Intrinsics of every ``stride``-th pixel of a grid (its pixels 0, s, 2s, ... become 0, 1, 2, ...): K's first
    two rows divided by s (unlike :func:`scale_intrinsics`, which averages pixels). numpy (float64) or torch, any
    leading batch shape; returns a new array."""
    K = K_33.clone() if isinstance(K_33, torch.Tensor) else np.array(K_33, dtype=np.float64, copy=True)
    K[..., :2, :] /= stride
    return K


def scale_intrinsics(K_b33: torch.Tensor, sx: float, sy: float) -> torch.Tensor:
    """Intrinsics of an image resized by factors (sx, sy) (new_size = old_size * s).

    With pixel centres at integer coordinates, a pixel edge at -0.5 stays at -0.5, hence
    ``fx' = fx*sx``, ``cx' = (cx + 0.5)*sx - 0.5`` and the same for y. The skew scales with sx.
    Accepts any leading batch shape (``...x3x3``); returns a new tensor.
    """
    K = K_b33.clone()
    K[..., 0, 0] = K_b33[..., 0, 0] * sx
    K[..., 0, 1] = K_b33[..., 0, 1] * sx
    K[..., 0, 2] = (K_b33[..., 0, 2] + 0.5) * sx - 0.5
    K[..., 1, 1] = K_b33[..., 1, 1] * sy
    K[..., 1, 2] = (K_b33[..., 1, 2] + 0.5) * sy - 0.5
    return K


def _invert_K(K_b33: torch.Tensor) -> torch.Tensor:
    """Closed-form inverse of upper-triangular pinhole intrinsics [[fx,s,cx],[0,fy,cy],[0,0,1]]."""
    fx, s, cx = K_b33[..., 0, 0], K_b33[..., 0, 1], K_b33[..., 0, 2]
    fy, cy = K_b33[..., 1, 1], K_b33[..., 1, 2]
    zero = torch.zeros_like(fx)
    one = torch.ones_like(fx)
    row0 = torch.stack([1.0 / fx, -s / (fx * fy), (s * cy - cx * fy) / (fx * fy)], dim=-1)
    row1 = torch.stack([zero, 1.0 / fy, -cy / fy], dim=-1)
    row2 = torch.stack([zero, zero, one], dim=-1)
    return torch.stack([row0, row1, row2], dim=-2)


# ----------------------------------------------------------------------------------------------
# SE(3) / SO(3)
# ----------------------------------------------------------------------------------------------

def make_se3(R_b33: torch.Tensor, t_b3: torch.Tensor) -> torch.Tensor:
    """Assemble 4x4 transforms from rotations ``...x3x3`` and translations ``...x3``."""
    batch = R_b33.shape[:-2]
    T = torch.zeros(*batch, 4, 4, dtype=R_b33.dtype, device=R_b33.device)
    T[..., :3, :3] = R_b33
    T[..., :3, 3] = t_b3
    T[..., 3, 3] = 1.0
    return T


def invert_se3(T_b44: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid transforms (``T_a_b -> T_b_a``): ``[R^T, -R^T t]``. Any leading batch shape."""
    R = T_b44[..., :3, :3]
    t = T_b44[..., :3, 3:]
    Rt = R.transpose(-1, -2)
    return make_se3(Rt, -(Rt @ t)[..., 0])


def transform_points(T_b44: torch.Tensor, points_b3n: torch.Tensor) -> torch.Tensor:
    """Apply ``T`` (Bx4x4) to points (Bx3xN): ``R X + t``."""
    return T_b44[..., :3, :3] @ points_b3n + T_b44[..., :3, 3:]


def _hat(w_b3: torch.Tensor) -> torch.Tensor:
    x, y, z = w_b3.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([torch.stack([o, -z, y], -1),
                        torch.stack([z, o, -x], -1),
                        torch.stack([-y, x, o], -1)], -2)


def so3_exp(omega_b3: torch.Tensor) -> torch.Tensor:
    """Rodrigues: rotation matrix of an axis-angle vector (radians). Smooth at zero."""
    theta2 = (omega_b3 * omega_b3).sum(-1)[..., None, None]
    theta = torch.sqrt(theta2.clamp_min(1e-30))
    small = theta2 < 1e-8
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / theta2.clamp_min(1e-30))
    W = _hat(omega_b3)
    eye = torch.eye(3, dtype=omega_b3.dtype, device=omega_b3.device).expand_as(W)
    return eye + a * W + b * (W @ W)


def rotation_angle(R_b33: torch.Tensor) -> torch.Tensor:
    """Rotation angle in radians, in [0, pi] (atan2 form: accurate for small and large angles)."""
    tr = R_b33[..., 0, 0] + R_b33[..., 1, 1] + R_b33[..., 2, 2]
    v = torch.stack([R_b33[..., 2, 1] - R_b33[..., 1, 2],
                     R_b33[..., 0, 2] - R_b33[..., 2, 0],
                     R_b33[..., 1, 0] - R_b33[..., 0, 1]], -1)
    return torch.atan2(0.5 * v.norm(dim=-1), 0.5 * (tr - 1.0))


def se3_exp(xi_b6: torch.Tensor) -> torch.Tensor:
    """Transform of a twist ``(rho, omega)`` (translation part first) by the SE(3) exponential."""
    rho, omega = xi_b6[..., :3], xi_b6[..., 3:]
    R = so3_exp(omega)
    theta2 = (omega * omega).sum(-1)[..., None, None]
    theta = torch.sqrt(theta2.clamp_min(1e-30))
    small = theta2 < 1e-8
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / theta2.clamp_min(1e-30))
    c = torch.where(small, 1.0 / 6.0 - theta2 / 120.0,
                    (theta - torch.sin(theta)) / (theta2 * theta).clamp_min(1e-30))
    W = _hat(omega)
    eye = torch.eye(3, dtype=xi_b6.dtype, device=xi_b6.device).expand_as(W)
    V = eye + b * W + c * (W @ W)
    return make_se3(R, (V @ rho[..., None])[..., 0])


# ----------------------------------------------------------------------------------------------
# Projection
# ----------------------------------------------------------------------------------------------

def pixel_grid(h: int, w: int, dtype=torch.float32, device=None) -> torch.Tensor:
    """Homogeneous pixel coordinates ``[u, v, 1]`` of an h x w image, shape (3, h*w), row-major.

    The grids of the last few sizes are kept (a keyframe asks for the same few grids a dozen times): the tensor
    returned is shared, so callers must not write into it."""
    return _pixel_grid(int(h), int(w), dtype, torch.device('cpu') if device is None else torch.device(device))


@functools.lru_cache(maxsize=8)
def _pixel_grid(h: int, w: int, dtype, device: torch.device) -> torch.Tensor:
    with torch.inference_mode(False):       # a normal tensor, whatever mode the first caller ran in
        return _fresh_pixel_grid(h, w, dtype, device)


def _fresh_pixel_grid(h: int, w: int, dtype, device: torch.device) -> torch.Tensor:
    v, u = torch.meshgrid(torch.arange(h, dtype=dtype, device=device),
                          torch.arange(w, dtype=dtype, device=device), indexing='ij')
    return torch.stack([u.reshape(-1), v.reshape(-1), torch.ones(h * w, dtype=dtype, device=device)], 0)


def backproject(depth_bhw: torch.Tensor, K_b33: torch.Tensor) -> torch.Tensor:
    """Camera-frame 3-D points ``X = depth * K^-1 [u, v, 1]`` of every pixel, shape (B, 3, H, W)."""
    B, H, W = depth_bhw.shape
    rays = _invert_K(K_b33) @ pixel_grid(H, W, depth_bhw.dtype, depth_bhw.device)  # B,3,HW
    return (rays * depth_bhw.reshape(B, 1, H * W)).reshape(B, 3, H, W)


def project(points_b3n: torch.Tensor, K_b33: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """Pinhole projection: returns pixel coordinates (B, 2, N) and z-depth (B, N).

    Points with ``z <= Z_EPS`` are behind (or on) the camera plane; their uv are computed with z
    replaced by 1 (finite, gradient-safe, meaningless) - callers must mask them with ``z > Z_EPS``.
    """
    p = K_b33 @ points_b3n
    z = points_b3n[:, 2]
    zs = torch.where(z > Z_EPS, p[:, 2], torch.ones_like(z))
    return p[:, :2] / zs[:, None], z


def _depths_bd(depths_d: torch.Tensor, B: int, like: torch.Tensor) -> torch.Tensor:
    d = torch.as_tensor(depths_d, dtype=like.dtype, device=like.device)
    if d.dim() == 1:
        d = d[None].expand(B, -1)
    return d


def inverse_depth_index(depth: torch.Tensor, d_min, d_max, D: int) -> torch.Tensor:
    """Fractional plane index of a depth for D planes uniform in inverse depth (0 at d_min).

    Non-positive depths give NaN. (``dpv.depth_to_index`` is the public alias.)
    """
    inv = 1.0 / torch.where(depth > 0, depth, torch.full_like(depth, float('nan')))
    inv_min = 1.0 / d_min
    inv_max = 1.0 / d_max
    return (inv_min - inv) / (inv_min - inv_max) * (D - 1)


def inverse_depth_step(d_min, d_max, D: int) -> float:
    """Spacing (1/m) of D planes uniform in inverse depth from d_min to d_max: one plane index in inverse depth
    (the slope of :func:`inverse_depth_index`)."""
    return (1.0 / d_min - 1.0 / d_max) / (D - 1)


# ----------------------------------------------------------------------------------------------
# Warps
# ----------------------------------------------------------------------------------------------

def _norm_matrix(h: int, w: int, like: torch.Tensor) -> torch.Tensor:
    """3x3 matrix taking pixel coordinates to grid_sample's [-1, 1] (align_corners=True)."""
    N = torch.zeros(3, 3, dtype=like.dtype, device=like.device)
    N[0, 0] = 2.0 / max(w - 1, 1)
    N[0, 2] = -1.0
    N[1, 1] = 2.0 / max(h - 1, 1)
    N[1, 2] = -1.0
    N[2, 2] = 1.0
    return N


def _sweep_grid(K_ref_b33, K_src_b33, T_src_ref_b44, depths_bd, H, W, Hs, Ws):
    """Normalised source sampling coordinates of every (plane, ref pixel).

    Returns (grid_bdn2 in grid_sample units, z_bdn = source depth, front_bdn = z > Z_EPS), where
    n runs over the H*W reference pixels. Points behind the source camera get grid = -2 (outside).
    The projection and the normalisation are folded into one 3x3 matrix per batch element, so the
    per-voxel work is one multiply-add per coordinate and one division.
    """
    pix = pixel_grid(H, W, K_ref_b33.dtype, K_ref_b33.device)                      # 3,HW
    NK = _norm_matrix(Hs, Ws, K_src_b33) @ K_src_b33                                # B,3,3
    M = NK @ T_src_ref_b44[:, :3, :3] @ _invert_K(K_ref_b33)                        # B,3,3
    o = NK @ T_src_ref_b44[:, :3, 3:]                                               # B,3,1
    dir_ = (M @ pix).transpose(1, 2)                                                # B,HW,3
    p = torch.addcmul(o.transpose(1, 2)[:, None], depths_bd[:, :, None, None], dir_[:, None])  # B,D,HW,3
    z = p[..., 2]
    front = z > Z_EPS
    zs = torch.where(front, z, torch.ones_like(z))
    grid = p[..., :2] / zs[..., None]
    grid = torch.where(front[..., None], grid, torch.full_like(grid, -2.0))
    return grid, z, front


def _grid_inside(grid, h: int, w: int, tol_px: float) -> torch.Tensor:
    """True where normalised coordinates lie within [-tol, size-1+tol] pixels on both axes."""
    tx = 1.0 + 2.0 * tol_px / max(w - 1, 1)
    ty = 1.0 + 2.0 * tol_px / max(h - 1, 1)
    return (grid[..., 0].abs() <= tx) & (grid[..., 1].abs() <= ty)


def plane_sweep_warp(src_bchw: torch.Tensor, K_ref_b33: torch.Tensor, K_src_b33: torch.Tensor,
                     T_src_ref_b44: torch.Tensor, depths_d: torch.Tensor,
                     ref_hw: Optional[Sequence[int]] = None) -> Tuple[torch.Tensor, torch.Tensor]:
    """Warp a source image / feature map onto D fronto-parallel planes of the reference camera.

    For reference pixel (u, v) and plane depth d: ``X_ref = d K_ref^-1 [u, v, 1]``,
    ``X_src = T_src_ref X_ref``, and the source is sampled bilinearly at ``K_src X_src``.

    Args:
        src_bchw: (B, C, Hs, Ws) source image or features (K_src describes this grid).
        K_ref_b33, K_src_b33: (B, 3, 3) intrinsics of the reference grid and the source grid.
        T_src_ref_b44: (B, 4, 4) maps reference-camera points into the source camera.
        depths_d: (D,) plane depths (or (B, D) per batch element), in metres.
        ref_hw: (H, W) of the reference grid; defaults to the source size.
    Returns:
        warped_bcdhw: (B, C, D, H, W), zero where the sample falls outside the source.
        valid_bdhw: (B, D, H, W) bool, True where the sample lies in front of and inside the source.
    """
    B, C, Hs, Ws = src_bchw.shape
    H, W = (Hs, Ws) if ref_hw is None else (int(ref_hw[0]), int(ref_hw[1]))
    dt = src_bchw.dtype
    K_ref_b33 = K_ref_b33.to(dt).expand(B, 3, 3)
    K_src_b33 = K_src_b33.to(dt).expand(B, 3, 3)
    T_src_ref_b44 = T_src_ref_b44.to(dt).expand(B, 4, 4)
    d = _depths_bd(depths_d, B, src_bchw)
    D = d.shape[1]
    grid, _, front = _sweep_grid(K_ref_b33, K_src_b33, T_src_ref_b44, d, H, W, Hs, Ws)
    valid = front & _grid_inside(grid, Hs, Ws, BOUNDS_TOL)
    warped = F.grid_sample(src_bchw, grid.reshape(B, D * H, W, 2), mode='bilinear', padding_mode='zeros',
                           align_corners=True)
    return warped.reshape(B, C, D, H, W), valid.reshape(B, D, H, W)


def warp_volume(logp_bdhw: torch.Tensor, K_b33: torch.Tensor, T_b_a_b44: torch.Tensor,
                depths_d: torch.Tensor, return_valid: bool = False, stride: int = 1):
    """Predict step of the DPV filter (paper eq. 5): resample camera A's DPV into camera B's frustum.

    Every voxel (plane k, pixel u, v) of camera B is mapped to camera A with ``T_a_b = T_b_a^-1``,
    projected with K (both volumes share K and the planes) and its A-depth converted to a fractional
    plane index (planes uniform in inverse depth between ``depths_d[0]`` and ``depths_d[-1]``). A's
    *probabilities* are sampled there trilinearly (a mixture, so a sharp peak spreads over
    neighbouring voxels rather than vanishing). Voxels of B that lie outside A's frustum get the
    uniform prior 1/D: behind A, or beyond half a voxel outside A's grid (pixel u outside
    [-0.5, W-0.5], v outside [-0.5, H-0.5], plane index outside [-0.5, D-0.5] - each voxel covers
    +-0.5 of its index; the outer half-voxel takes the border value). Without that half-voxel
    margin the end planes of a moving camera would be reset to 1/D at every step. Each B ray is then
    renormalised (log-softmax over dim 1). A batch element whose pose is exactly the identity is
    returned unchanged (normalised).

    Args:
        logp_bdhw: (B, D, H, W) log-probabilities of camera A's DPV.
        K_b33: (B, 3, 3) intrinsics of the volume grid (H x W).
        T_b_a_b44: (B, 4, 4) maps camera-A points into camera B (relative pose A -> B).
        depths_d: (D,) plane depths (uniform in inverse depth, ascending).
        return_valid: also return (B, D, H, W) bool, True where the voxel was seen by A.
        stride: B's volume only at every ``stride``-th pixel of each axis (pixels 0, s, 2s, ...; shape
            (B, D, ceil(H / s), ceil(W / s))): the full warp subsampled, at 1/s^2 of its cost.
    Returns:
        logp_bdhw of camera B (and the valid mask when asked).
    """
    B, D, H, W = logp_bdhw.shape
    stride = int(stride)
    if stride < 1:
        raise ValueError(f'stride must be >= 1, got {stride}')
    Hb, Wb = -(-H // stride), -(-W // stride)
    dt = logp_bdhw.dtype
    T_b_a_b44 = T_b_a_b44.expand(B, 4, 4)
    K = K_b33.to(dt).expand(B, 3, 3)
    # A pose that is exactly the identity (a static camera) returns the input: resampling would
    # otherwise leak float32 rounding into sharp volumes frame after frame.
    eye = torch.eye(4, dtype=T_b_a_b44.dtype, device=T_b_a_b44.device)
    is_identity = (T_b_a_b44 == eye).reshape(B, 16).all(1)
    if bool(is_identity.all()):
        out = torch.log_softmax(logp_bdhw, dim=1)[..., ::stride, ::stride]
        return (out, torch.ones_like(out, dtype=torch.bool)) if return_valid else out
    depths = torch.as_tensor(depths_d, dtype=dt, device=logp_bdhw.device)
    d_bd = depths[None].expand(B, -1) if depths.dim() == 1 else depths
    T_a_b = invert_se3(T_b_a_b44.to(dt))
    K_b = K if stride == 1 else subsampled_intrinsics(K, stride)
    grid_xy, z, front = _sweep_grid(K_b, K, T_a_b, d_bd, Hb, Wb, H, W)
    # normalised plane coordinate, linear in 1/z: index 0 at d_min -> -1, index D-1 at d_max -> +1
    inv_min, inv_max = 1.0 / d_bd[:, :1, None], 1.0 / d_bd[:, -1:, None]
    gz = torch.where(front, (2.0 / z.where(front, torch.ones_like(z)) - inv_min - inv_max) / (inv_max - inv_min),
                     torch.full_like(z, -2.0))
    half = 1.0 / max(D - 1, 1)                       # half a plane in normalised units
    inside = front & _grid_inside(grid_xy, H, W, 0.5) & (gz.abs() <= 1.0 + half)
    grid = torch.cat([grid_xy, gz[..., None]], -1).reshape(B, D, Hb, Wb, 3)
    prob = torch.exp(logp_bdhw)[:, None]                                   # B,1,D,H,W
    sampled = F.grid_sample(prob, grid, mode='bilinear', padding_mode='border', align_corners=True)[:, 0]
    inside = inside.reshape(B, D, Hb, Wb)
    sampled = torch.where(inside, sampled, torch.full_like(sampled, 1.0 / D))
    out = torch.log_softmax(torch.log(sampled.clamp_min(1e-30)), dim=1)
    if bool(is_identity.any()):
        keep = is_identity.reshape(B, 1, 1, 1)
        out = torch.where(keep, torch.log_softmax(logp_bdhw, dim=1)[..., ::stride, ::stride], out)
        inside = inside | keep
    return (out, inside) if return_valid else out


def warp_image_with_depth(src_bchw: torch.Tensor, depth_bhw: torch.Tensor, K_ref_b33: torch.Tensor,
                          K_src_b33: torch.Tensor, T_src_ref_b44: torch.Tensor
                          ) -> Tuple[torch.Tensor, torch.Tensor]:
    """Warp a source image into the reference view using the reference depth map.

    ``X_ref = depth K_ref^-1 [u, v, 1]``, ``X_src = T_src_ref X_ref``, sample src at ``K_src X_src``.

    Args:
        src_bchw: (B, C, Hs, Ws) source image (K_src describes this grid).
        depth_bhw: (B, H, W) reference z-depth in metres (<= 0 or non-finite = no depth).
        K_ref_b33, K_src_b33: (B, 3, 3); T_src_ref_b44: (B, 4, 4).
    Returns:
        warped_bchw: (B, C, H, W) (zero where invalid), valid_bhw: (B, H, W) bool - the pixel has a
        depth, lands in front of the source camera and inside the source image.
    """
    B, C, Hs, Ws = src_bchw.shape
    _, H, W = depth_bhw.shape
    dt = src_bchw.dtype
    K_ref_b33, K_src_b33 = K_ref_b33.to(dt).expand(B, 3, 3), K_src_b33.to(dt).expand(B, 3, 3)
    T_src_ref_b44 = T_src_ref_b44.to(dt).expand(B, 4, 4)
    has_depth = torch.isfinite(depth_bhw) & (depth_bhw > 0)
    depth = torch.where(has_depth, depth_bhw.to(dt), torch.ones_like(depth_bhw, dtype=dt))
    pts = backproject(depth, K_ref_b33).reshape(B, 3, H * W)
    uv, z = project(transform_points(T_src_ref_b44, pts), K_src_b33)
    front = z > Z_EPS
    grid = (uv.transpose(1, 2) * torch.tensor([2.0 / max(Ws - 1, 1), 2.0 / max(Hs - 1, 1)], dtype=dt,
                                               device=uv.device) - 1.0)
    grid = torch.where(front[..., None], grid, torch.full_like(grid, -2.0))
    valid = has_depth.reshape(B, H * W) & front & _grid_inside(grid, Hs, Ws, BOUNDS_TOL)
    warped = F.grid_sample(src_bchw, grid.reshape(B, H, W, 2), mode='bilinear', padding_mode='zeros',
                           align_corners=True)
    valid = valid.reshape(B, H, W)
    return warped * valid[:, None].to(dt), valid


# ------------------------------------------------------------------------------------------------------
# resampling between grids of one camera
# ------------------------------------------------------------------------------------------------------


def camera_grid_affine(K_src_33, K_dst_33) -> Tuple[float, float, float, float]:
    """(ax, ay, bx, by): destination pixel (u, v) of camera grid ``K_dst`` lies at source coordinate
    ``(ax u + bx, ay v + by)`` of grid ``K_src``, both grids of the same pinhole camera (scale and offset only):
    ``u_src = fx_src / fx_dst * (u - cx_dst) + cx_src``."""
    Ks = torch.as_tensor(K_src_33, dtype=torch.float64).reshape(3, 3)
    Kd = torch.as_tensor(K_dst_33, dtype=torch.float64).reshape(3, 3)
    ax = float(Ks[0, 0] / Kd[0, 0])
    ay = float(Ks[1, 1] / Kd[1, 1])
    bx = float(Ks[0, 2]) - ax * float(Kd[0, 2])
    by = float(Ks[1, 2]) - ay * float(Kd[1, 2])
    return ax, ay, bx, by


def camera_resample_grid(affine: Tuple[float, float, float, float], src_hw: Tuple[int, int],
                         dst_hw: Tuple[int, int], dtype: torch.dtype) -> torch.Tensor:
    """The ``grid_sample(align_corners=True)`` grid, (1, H_dst, W_dst, 2), that reads a map of size ``src_hw`` at
    the source coordinates of :func:`camera_grid_affine` (pixel centres at integer coordinates)."""
    ax, ay, bx, by = affine
    Hs, Ws = int(src_hw[0]), int(src_hw[1])
    Hd, Wd = int(dst_hw[0]), int(dst_hw[1])
    u = torch.arange(Wd, dtype=torch.float64) * ax + bx
    v = torch.arange(Hd, dtype=torch.float64) * ay + by
    gx = (2.0 * u / max(Ws - 1, 1) - 1.0).to(dtype)
    gy = (2.0 * v / max(Hs - 1, 1) - 1.0).to(dtype)
    gyy, gxx = torch.meshgrid(gy, gx, indexing='ij')
    return torch.stack([gxx, gyy], -1)[None]


def resample_to_camera(x_bchw: torch.Tensor, K_src_33, K_dst_33, dst_hw: Tuple[int, int],
                       mode: str = 'bilinear') -> torch.Tensor:
    """Resample a map defined on camera grid ``K_src`` (its own size) onto grid ``K_dst`` of size dst_hw.

    Both grids belong to the same pinhole camera (they differ only in scale and offset, e.g. an image
    and its resized copy, or an image and its DPV's stride-4 grid), so destination pixel u reads source
    coordinate ``u_src = fx_src/fx_dst * (u - cx_dst) + cx_src`` (same for v). Sampled with
    ``grid_sample(align_corners=True)`` on pixel-centre coordinates, borders clamped. ``mode``:
    'bilinear' or 'nearest'.
    """
    B, C, Hs, Ws = x_bchw.shape
    dt, dev = (x_bchw.dtype if x_bchw.is_floating_point() else torch.float32), x_bchw.device
    grid = camera_resample_grid(camera_grid_affine(K_src_33, K_dst_33), (Hs, Ws), dst_hw, dt)
    grid = grid.expand(B, int(dst_hw[0]), int(dst_hw[1]), 2).to(dev)
    src = x_bchw if x_bchw.is_floating_point() else x_bchw.to(dt)
    return F.grid_sample(src, grid, mode=mode, padding_mode='border', align_corners=True)
