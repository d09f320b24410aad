"""Tests of dpv_sensor.core.geometry: intrinsics, SE(3), projection and the warps (tiny analytic scenes)."""
import math
import os
import sys

import numpy as np
import pytest
import torch

sys.path.insert(0, os.path.dirname(__file__))
from synthetic_planes import DT, intrinsics, render_plane_pair, rot_x, rot_y, rot_z, se3  # noqa: E402

from dpv_sensor.core import geometry as G  # noqa: E402
from dpv_sensor.core import pose_math as PM  # noqa: E402
from dpv_sensor.core.dpv import depth_planes, depth_to_index  # noqa: E402


# ------------------------------------------------------------------ intrinsics, SE(3)

def test_scale_intrinsics_pixel_centres():
    K = intrinsics(64, 48, 50.0)            # cx = 31.5, cy = 23.5: the centre of a 64x48 image
    K2 = G.scale_intrinsics(K, 0.5, 0.25)   # -> 32x12 image
    assert K2[0, 0, 0].item() == pytest.approx(25.0)
    assert K2[0, 1, 1].item() == pytest.approx(12.5)
    assert K2[0, 0, 2].item() == pytest.approx(15.5)   # centre of 32 pixels
    assert K2[0, 1, 2].item() == pytest.approx(5.5)    # centre of 12 pixels
    assert torch.equal(K, intrinsics(64, 48, 50.0))    # input untouched


def test_invert_and_compose():
    T = se3(rot_z(0.4) @ rot_x(-0.3), (0.5, -1.0, 2.0))
    Ti = G.invert_se3(T)
    eye = torch.eye(4, dtype=DT)[None]
    assert torch.allclose(T @ Ti, eye, atol=1e-12)
    assert torch.allclose(Ti @ T, eye, atol=1e-12)
    # by hand: inverse of a pure translation is the negative translation
    assert torch.allclose(G.invert_se3(se3(t=(1.0, 2.0, 3.0))), se3(t=(-1.0, -2.0, -3.0)))
    # composing two rotations about z adds the angles; T_a_c = T_a_b T_b_c on points
    Tab, Tbc = se3(rot_z(0.3), (1.0, 0.0, 0.0)), se3(rot_z(0.5), (0.0, 2.0, 0.0))
    Tac = Tab @ Tbc
    assert torch.allclose(Tac[0, :3, :3], rot_z(0.8), atol=1e-12)
    X_c = torch.tensor([[[0.3], [0.2], [1.0]]], dtype=DT)
    assert torch.allclose(G.transform_points(Tac, X_c), G.transform_points(Tab, G.transform_points(Tbc, X_c)))


def _np(T):
    return T[0].numpy()


def test_interpolate_translation_endpoints_and_midpoint():
    T0, T1 = _np(se3(t=(0.0, 0.0, 0.0))), _np(se3(t=(2.0, -4.0, 1.0)))
    np.testing.assert_allclose(PM.interpolate_pose(T0, T1, 0.0), T0)
    np.testing.assert_allclose(PM.interpolate_pose(T0, T1, 1.0), T1)
    np.testing.assert_allclose(PM.interpolate_pose(T0, T1, 0.5), _np(se3(t=(1.0, -2.0, 0.5))), atol=1e-12)


def test_interpolate_rotation_about_z():
    T0 = _np(se3(rot_z(0.0), (0.0, 0.0, 0.0)))
    T1 = _np(se3(rot_z(math.radians(60)), (1.0, 0.0, 0.0)))
    for a, deg in [(0.0, 0.0), (0.25, 15.0), (0.5, 30.0), (0.75, 45.0), (1.0, 60.0)]:
        T = PM.interpolate_pose(T0, T1, a)
        np.testing.assert_allclose(T[:3, :3], rot_z(math.radians(deg)).numpy(), atol=1e-9)
        np.testing.assert_allclose(T[:3, 3], [a, 0.0, 0.0], atol=1e-12)
    # shortest arc across +-180 deg: 170 deg -> -170 deg passes through 180, not 0
    mid = PM.interpolate_pose(_np(se3(rot_z(math.radians(170)))), _np(se3(rot_z(math.radians(-170)))), 0.5)
    np.testing.assert_allclose(mid[:3, :3], rot_z(math.pi).numpy(), atol=1e-9)


def test_quaternion_roundtrip_and_so3():
    torch.manual_seed(0)
    w = torch.randn(16, 3, dtype=DT) * 1.5
    R = G.so3_exp(w)
    assert torch.allclose(R @ R.transpose(-1, -2), torch.eye(3, dtype=DT).expand(16, 3, 3), atol=1e-12)
    for R_33 in R.numpy():
        q = PM.matrix_to_quat(R_33)
        assert q[3] >= 0 and np.linalg.norm(q) == pytest.approx(1.0)
        np.testing.assert_allclose(PM.quat_to_matrix(q), R_33, atol=1e-10)
    angles = torch.remainder(w.norm(dim=-1) + math.pi, 2 * math.pi).sub(math.pi).abs()
    assert torch.allclose(G.rotation_angle(R), angles, atol=1e-9)
    np.testing.assert_allclose([PM.rotation_angle_np(R_33) for R_33 in R.numpy()], angles.numpy(), atol=1e-9)
    assert G.rotation_angle(rot_z(math.radians(30))[None]).item() == pytest.approx(math.radians(30))
    T = G.se3_exp(torch.tensor([[1.0, 2.0, 3.0, 0.0, 0.0, 0.0]], dtype=DT))
    assert torch.allclose(T, se3(t=(1.0, 2.0, 3.0)))


# ------------------------------------------------------------------ projection

def test_backproject_project_roundtrip():
    K = intrinsics(8, 6, 10.0)
    depth = torch.linspace(0.5, 3.0, 48, dtype=DT).reshape(1, 6, 8)
    P = G.backproject(depth, K)
    assert torch.allclose(P[0, 2], depth[0])
    # by hand: pixel (u=7, v=0) at depth 2 -> X = 2*(7-3.5)/10
    assert P[0, 0, 0, 7].item() == pytest.approx(depth[0, 0, 7].item() * 3.5 / 10.0)
    uv, z = G.project(P.reshape(1, 3, -1), K)
    v, u = torch.meshgrid(torch.arange(6, dtype=DT), torch.arange(8, dtype=DT), indexing='ij')
    assert torch.allclose(uv[0, 0], u.reshape(-1)) and torch.allclose(uv[0, 1], v.reshape(-1))
    assert torch.allclose(z[0], depth.reshape(-1))


# ------------------------------------------------------------------ plane-sweep warp

W_, H_ = 64, 48
MOTIONS = {
    'tx': se3(t=(0.25, 0.0, 0.0)),
    'ty': se3(t=(0.0, -0.25, 0.0)),
    'tz': se3(t=(0.0, 0.0, -0.2)),   # source camera closer: no minification aliasing
    'rot': se3(rot_y(math.radians(4.0)) @ rot_x(math.radians(-3.0)), (-0.2, 0.1, 0.05)),
}


def _sweep_costs(T_src_ref, k, D=16):
    K = intrinsics(W_, H_, 60.0)
    planes = depth_planes(0.5, 5.0, D, dtype=DT)
    z = planes[k].item()
    ref, src = render_plane_pair(K, K, T_src_ref, z, H_, W_)
    warped, valid = G.plane_sweep_warp(src, K, K, T_src_ref, planes)
    err = (warped - ref[:, :, None]).abs()[:, 0]          # B,D,H,W
    vf = valid.to(DT)
    cost = (err * vf).sum((0, 2, 3)) / vf.sum((0, 2, 3)).clamp_min(1)
    cost = torch.where(vf.mean((0, 2, 3)) > 0.3, cost, torch.full_like(cost, float('inf')))
    return cost


@pytest.mark.parametrize('motion', list(MOTIONS))
@pytest.mark.parametrize('k', [4, 9])
def test_plane_sweep_minimum_at_true_plane(motion, k):
    cost = _sweep_costs(MOTIONS[motion], k)
    assert int(cost.argmin()) == k, cost
    # at the true plane only bilinear-interpolation error remains: far below the neighbours
    assert cost[k] < 0.02, cost
    assert cost[k] < 0.5 * min(cost[k - 1], cost[k + 1]), cost


def test_plane_sweep_identity_and_valid():
    K = intrinsics(12, 10, 10.0)
    src = torch.rand(2, 3, 10, 12, dtype=DT)
    planes = depth_planes(1.0, 4.0, 5, dtype=DT)
    T = se3().expand(2, 4, 4)
    warped, valid = G.plane_sweep_warp(src, K.expand(2, 3, 3), K.expand(2, 3, 3), T, planes)
    assert warped.shape == (2, 3, 5, 10, 12) and valid.shape == (2, 5, 10, 12)
    assert valid.all()
    assert torch.allclose(warped, src[:, :, None].expand_as(warped), atol=1e-12)
    # a large x-translation pushes near planes out of the source image: zeros and invalid there
    warped, valid = G.plane_sweep_warp(src, K.expand(2, 3, 3), K.expand(2, 3, 3), se3(t=(2.0, 0, 0)).expand(2, 4, 4),
                                       planes)
    assert not valid[:, 0].any() and (warped[:, :, 0] == 0).all()
    # ref_hw: a half-size reference grid reading from the full-size source
    K_ref = G.scale_intrinsics(K, 0.5, 0.5)
    warped, valid = G.plane_sweep_warp(src, K_ref.expand(2, 3, 3), K.expand(2, 3, 3), T, planes, ref_hw=(5, 6))
    assert warped.shape == (2, 3, 5, 5, 6) and valid.all()


def test_plane_sweep_gradcheck():
    torch.manual_seed(1)
    K = intrinsics(6, 5, 5.0)
    planes = torch.tensor([1.0, 1.7, 3.1], dtype=DT)
    src = torch.rand(1, 2, 5, 6, dtype=DT, requires_grad=True)
    T = se3(rot_y(0.05), (0.13, -0.07, 0.05)).clone().requires_grad_(True)

    def f(s, T_):
        return G.plane_sweep_warp(s, K, K, T_, planes)[0]

    assert torch.autograd.gradcheck(f, (src, T), eps=1e-6, atol=1e-5)


# ------------------------------------------------------------------ volume warp

def test_warp_volume_identity():
    torch.manual_seed(0)
    D, H, W = 8, 6, 7
    logp = torch.log_softmax(torch.randn(2, D, H, W, dtype=DT) * 3, 1)
    K = intrinsics(W, H, 6.0).expand(2, 3, 3)
    planes = depth_planes(0.5, 4.0, D, dtype=DT)
    # exactly the identity: returned unchanged (any dtype; a static camera must not blur its DPV)
    out = G.warp_volume(logp, K, se3().expand(2, 4, 4), planes)
    assert torch.allclose(out, logp, atol=1e-5)
    out32 = G.warp_volume(logp.float(), K.float(), se3().float(), planes.float())
    assert torch.allclose(out32.double(), logp, atol=1e-5)
    # identity up to 1e-12 m goes through the full resampling path (float64) and still returns the input
    out = G.warp_volume(logp, K, se3(t=(1e-12, 0.0, 0.0)).expand(2, 4, 4), planes)
    assert torch.allclose(out, logp, atol=1e-5)
    # float32 through the resampling path: the probabilities agree
    out32 = G.warp_volume(logp.float(), K.float(), se3(t=(1e-9, 0.0, 0.0)).float(), planes.float())
    assert torch.allclose(out32.double().exp(), logp.exp(), atol=1e-5)


def _peaked_volume(D, H, W, u0, v0, k0):
    logits = torch.zeros(1, D, H, W, dtype=DT)
    logits[0, k0, v0, u0] = 25.0
    return torch.log_softmax(logits, 1)


@pytest.mark.parametrize('case', ['translate_x', 'general'])
def test_warp_volume_moves_peak_to_reprojected_voxel(case):
    D, H, W = 16, 24, 32
    K = intrinsics(W, H, 30.0)
    planes = depth_planes(0.5, 5.0, D, dtype=DT)
    u0, v0, k0 = 10, 8, 6
    X_a = planes[k0] * torch.linalg.inv(K[0]) @ torch.tensor([u0, v0, 1.0], dtype=DT)
    if case == 'translate_x':
        u1, v1, k1 = 13, 8, 6        # same depth, 3 pixels to the right
        R = torch.eye(3, dtype=DT)
    else:
        u1, v1, k1 = 20, 15, 9
        R = rot_y(math.radians(5.0)) @ rot_z(math.radians(10.0))
    X_b = planes[k1] * torch.linalg.inv(K[0]) @ torch.tensor([u1, v1, 1.0], dtype=DT)
    T_b_a = se3(R, X_b - R @ X_a)
    out = G.warp_volume(_peaked_volume(D, H, W, u0, v0, k0), K, T_b_a, planes)
    # the single most probable voxel of B is the re-projected one
    flat = int(out.exp().div(1.0 / D).reshape(-1).argmax())
    k, rem = divmod(flat, H * W)
    v, u = divmod(rem, W)
    assert (u, v, k) == (u1, v1, k1)
    # along that ray the DPV is peaked at the right plane, with the right expected depth
    # along that ray: the peak (~1 before renormalisation) at the right plane; every other voxel of
    # the ray samples A at <= 1/D (uniform rays, or the peaked ray's empty bins), so after
    # renormalisation p[k1] >= 1/(1 + (D-1)/D)
    p = out[0, :, v1, u1].exp()
    assert int(p.argmax()) == k1
    assert p[k1].item() >= 1.0 / (1.0 + (D - 1) / D) - 1e-9
    others = torch.cat([p[:k1], p[k1 + 1:]])
    assert others.max() < 0.05
    # rays far from the point stay (near) uniform
    assert torch.allclose(out[0, :, 0, W - 1].exp(), torch.full((D,), 1.0 / D, dtype=DT), atol=1e-6)


def test_subsampled_intrinsics_map_every_sth_pixel_to_the_next():
    # pixel (s*i, s*j) of the grid projects where pixel (i, j) of the subsampled grid does; numpy and torch alike
    K = np.array([[500.0, 0.0, 319.5], [0.0, 480.0, 239.5], [0.0, 0.0, 1.0]])
    X = np.array([0.3, -0.2, 2.0])
    for s in (2, 3):
        Ks = G.subsampled_intrinsics(K, s)
        np.testing.assert_allclose(Ks @ X / X[2], np.r_[(K @ X / X[2])[:2] / s, 1.0])
        Kt = G.subsampled_intrinsics(torch.as_tensor(K)[None], s)
        assert Kt.shape == (1, 3, 3) and np.allclose(Kt[0].numpy(), Ks)
    assert K[0, 0] == 500.0                                            # the input is not changed


@pytest.mark.parametrize('stride', [2, 3, 4])
def test_warp_volume_stride_is_the_full_warp_subsampled(stride):
    # every stride-th pixel of B (0, s, 2s, ...), odd sizes included: the same voxels as the whole warp, in float64
    torch.manual_seed(2)
    D, H, W = 8, 11, 13
    K = intrinsics(W, H, 9.0).expand(2, 3, 3)
    planes = depth_planes(0.5, 4.0, D, dtype=DT)
    logp = torch.log_softmax(torch.randn(2, D, H, W, dtype=DT) * 3, 1)
    T_b_a = torch.stack([se3(rot_y(0.04) @ rot_z(-0.02), (0.1, -0.05, 0.08))[0], se3()[0]])   # moved, static
    full, valid = G.warp_volume(logp, K, T_b_a, planes, return_valid=True)
    sub, sub_valid = G.warp_volume(logp, K, T_b_a, planes, return_valid=True, stride=stride)
    assert sub.shape == (2, D, -(-H // stride), -(-W // stride))
    assert torch.allclose(sub, full[..., ::stride, ::stride], atol=1e-9)
    assert torch.equal(sub_valid, valid[..., ::stride, ::stride])
    static = G.warp_volume(logp, K, se3().expand(2, 4, 4), planes, stride=stride)
    assert torch.equal(static, torch.log_softmax(logp, 1)[..., ::stride, ::stride])
    with pytest.raises(ValueError, match='stride'):
        G.warp_volume(logp, K, T_b_a, planes, stride=0)


def test_warp_volume_outside_frustum_is_uniform():
    D, H, W = 8, 12, 16
    K = intrinsics(W, H, 15.0)
    planes = depth_planes(0.5, 4.0, D, dtype=DT)
    logp = torch.log_softmax(torch.zeros(1, D, H, W, dtype=DT).index_fill(1, torch.tensor([3]), 10.0), 1)
    # turn 40 deg to the right: the right part of B's view was never seen by A
    T_b_a = se3(rot_y(math.radians(-40.0)))
    out, valid = G.warp_volume(logp, K, T_b_a, planes, return_valid=True)
    unseen = ~valid.any(1)
    assert unseen[0, :, -1].all() and not unseen[0, :, 0].any()
    assert torch.allclose(out[0][:, unseen[0]], torch.full_like(out[0][:, unseen[0]], -math.log(D)), atol=1e-9)
    # seen rays are normalised and keep a clear peak
    assert torch.allclose(out.exp().sum(1), torch.ones(1, H, W, dtype=DT))
    # (the plane is tilted in B, so its mass is spread over neighbouring planes)
    top3 = out[0, :, :, 0].exp().topk(3, dim=0).values.sum(0)
    assert (top3 > 0.95).all()
    # camera moved 10 m backwards: everything B sees at <= d_max lies outside A -> uniform
    out = G.warp_volume(logp, K, se3(t=(0.0, 0.0, 10.0)), planes)
    assert torch.allclose(out, torch.full_like(out, -math.log(D)), atol=1e-9)


def test_warp_volume_keeps_end_planes_for_small_motion():
    # 1 cm backwards: B's nearest plane lies 1 cm in front of A's d_min plane - within its half voxel,
    # so it keeps A's (here: near-zero) value instead of being reset to the uniform prior 1/D
    D, H, W = 8, 6, 8
    K = intrinsics(W, H, 6.0)
    planes = depth_planes(0.5, 4.0, D, dtype=DT)
    logp = torch.log_softmax(torch.zeros(1, D, H, W, dtype=DT).index_fill(1, torch.tensor([1]), 10.0), 1)
    out, valid = G.warp_volume(logp, K, se3(t=(0.0, 0.0, 0.01)), planes, return_valid=True)
    assert valid[0, :, 1:-1, 1:-1].all()
    assert (out[0, 0, 1:-1, 1:-1].exp() < 0.01).all()
    assert (out[0, 1, 1:-1, 1:-1].exp() > 0.8).all()
    # 0.5 m backwards: far outside the first plane's half voxel -> not seen by A
    out, valid = G.warp_volume(logp, K, se3(t=(0.0, 0.0, 0.5)), planes, return_valid=True)
    assert not valid[0, 0].any()


def test_warp_volume_gradcheck():
    torch.manual_seed(2)
    D, H, W = 4, 4, 5
    K = intrinsics(W, H, 4.0)
    planes = depth_planes(0.5, 3.0, D, dtype=DT)
    logp = torch.log_softmax(torch.randn(1, D, H, W, dtype=DT), 1).requires_grad_(True)
    T = se3(rot_x(0.03), (0.02, -0.01, 0.03))
    assert torch.autograd.gradcheck(lambda x: G.warp_volume(x, K, T, planes), (logp,), eps=1e-6, atol=1e-5)


# ------------------------------------------------------------------ image warp with depth

def test_warp_image_with_depth_reconstructs_reference():
    K = intrinsics(W_, H_, 60.0)
    T = MOTIONS['rot']
    z = 2.0
    ref, src = render_plane_pair(K, K, T, z, H_, W_)
    depth = torch.full((1, H_, W_), z, dtype=DT)
    depth[0, :2, :] = 0.0                              # no depth -> invalid
    warped, valid = G.warp_image_with_depth(src, depth, K, K, T)
    assert not valid[0, :2].any() and valid.float().mean() > 0.6
    err = (warped - ref).abs()[:, 0][valid]
    assert err.mean() < 0.01
    # a wrong depth gives a clearly worse alignment
    warped2, valid2 = G.warp_image_with_depth(src, depth * 1.5, K, K, T)
    assert (warped2 - ref).abs()[:, 0][valid2].mean() > 3 * err.mean()
    assert (warped[:, 0][~valid] == 0).all()
    # index helper consistent with the planes
    planes = depth_planes(0.5, 5.0, 16, dtype=DT)
    assert torch.allclose(depth_to_index(planes, 0.5, 5.0, 16), torch.arange(16, dtype=DT), atol=1e-9)


@pytest.mark.skipif(not torch.cuda.is_available(), reason='no CUDA device')
def test_cuda_matches_cpu():
    torch.manual_seed(3)
    K = intrinsics(16, 12, 12.0).float()
    planes = depth_planes(0.5, 4.0, 8)
    src = torch.rand(1, 3, 12, 16)
    T = se3(rot_y(0.05), (0.1, 0.0, 0.02)).float()
    a, va = G.plane_sweep_warp(src, K, K, T, planes)
    b, vb = G.plane_sweep_warp(src.cuda(), K.cuda(), K.cuda(), T.cuda(), planes.cuda())
    assert torch.allclose(a, b.cpu(), atol=1e-5) and torch.equal(va, vb.cpu())
    logp = torch.log_softmax(torch.randn(1, 8, 12, 16), 1)
    assert torch.allclose(G.warp_volume(logp, K, T, planes),
                          G.warp_volume(logp.cuda(), K.cuda(), T.cuda(), planes.cuda()).cpu(), atol=1e-4)


def test_numpy_rotation_angles_by_hand():
    from dpv_sensor.core.pose_math import quat_angle_deg, relative_pose_error_np, rotation_angle_np
    Rz90 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    assert rotation_angle_np(Rz90) == pytest.approx(np.pi / 2)
    assert rotation_angle_np(np.eye(3)) == 0.0
    Ta = np.eye(4)
    Ta[:3, 3] = [1.0, 0.0, 0.0]
    Tb = np.eye(4)
    Tb[:3, :3] = Rz90
    Tb[:3, 3] = [1.0, 2.0, 0.0]
    # in a's frame b sits 2 m along y and is turned 90 degrees
    t, r = relative_pose_error_np(Ta, Tb)
    assert (t, r) == (pytest.approx(2.0), pytest.approx(90.0))
    s = np.sqrt(0.5)
    assert quat_angle_deg(np.array([0, 0, 0, 1.0]), np.array([0, 0, s, s])) == pytest.approx(90.0)
    assert quat_angle_deg(np.array([0, 0, s, s]), -np.array([0, 0, s, s])) == pytest.approx(0.0, abs=1e-6)


def test_inverse_depth_step_is_the_slope_of_the_plane_index():
    from dpv_sensor.core.geometry import inverse_depth_index, inverse_depth_step
    step = inverse_depth_step(0.5, 8.0, 16)
    assert step == pytest.approx((2.0 - 0.125) / 15)
    i1 = float(inverse_depth_index(torch.tensor(1.0), 0.5, 8.0, 16))
    i2 = float(inverse_depth_index(torch.tensor(1.0 / (1.0 - step)), 0.5, 8.0, 16))
    assert i2 - i1 == pytest.approx(1.0, rel=1e-5)


def test_pixel_grid_by_hand_and_kept_usable_in_autograd():
    """A 2x3 grid is [u, v, 1] row-major; the kept grid of a size first asked for under inference_mode is an ordinary
    tensor, so a later backprojection with gradients through K and the depth still works."""
    with torch.inference_mode():
        first = G.pixel_grid(2, 3, torch.float64)
    assert not first.is_inference()
    assert first.tolist() == [[0, 1, 2, 0, 1, 2], [0, 0, 0, 1, 1, 1], [1, 1, 1, 1, 1, 1]]
    assert G.pixel_grid(2, 3, torch.float64) is first                      # kept, not rebuilt
    K = torch.tensor([[2.0, 0.0, 1.0], [0.0, 2.0, 0.5], [0.0, 0.0, 1.0]], dtype=torch.float64)[None].requires_grad_()
    depth = torch.full((1, 2, 3), 4.0, dtype=torch.float64, requires_grad=True)
    X = G.backproject(depth, K)                                             # x = 4 (u - 1) / 2 at v = 0
    assert X[0, 0, 0].tolist() == [-2.0, 0.0, 2.0]
    X.sum().backward()
    assert K.grad is not None and depth.grad is not None
