"""Pose refinement: photometric alignment, the gtsam sliding window, visual odometry.

Scenes are the exact ray-cast textured rectangles of ``synthetic_planes.render_scene`` at 80x60 (exact images
and depth, so errors come from the solver alone).
"""
from __future__ import annotations

import math
from types import SimpleNamespace

import gtsam
import numpy as np
import pytest
import torch

from synthetic_planes import Rect, intrinsics, render_scene, rot_x, rot_y, se3

from dpv_sensor.core.geometry import backproject, se3_exp, warp_image_with_depth
from dpv_sensor.core.photometric import (AlignmentConfig, align_photometric, inverse_depth_std_from_confidence,
                                   pose_error, resample_map, twist_to_gtsam_order)
from dpv_sensor.data.trajectory import corrupt_trajectory
from dpv_sensor.stream.visual_odometry import VisualOdometry, VisualOdometryConfig
from dpv_sensor.stream.window_refiner import PoseRefinerConfig, WindowKeyframe, WindowPoseRefiner, relative_pose_errors



@pytest.fixture(autouse=True, scope='module')
def one_torch_thread():
    """Tiny tensors: one intra-op thread is faster, and does not spin against other jobs on a shared CPU."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


W, H = 80, 60
K = intrinsics(W, H, 0.9 * W)
K_NP = K[0].numpy()
RECTS = [Rect(z=3.0, seed=0), Rect(z=1.8, x0=-0.6, x1=0.2, y0=-0.5, y1=0.4, seed=1),
         Rect(z=2.4, x0=0.3, x1=1.0, y0=-0.2, y1=0.8, seed=2)]


def render(T_world_cam):
    img, depth = render_scene(RECTS, K, T_world_cam, H, W)
    return img[0, 0].float(), depth[0].float()


def trajectory(n):
    """Camera moving right (5 cm per keyframe) while panning ~1 deg per keyframe."""
    return [se3(rot_y(0.017 * i) @ rot_x(0.005 * i), (0.05 * i - 0.1, 0.01 * i, 0.02 * i)) for i in range(n)]


@pytest.fixture(scope='module')
def pair():
    T_ref = se3()
    T_src = se3(rot_y(0.03) @ rot_x(-0.02), (0.12, 0.03, 0.05))
    I_ref, d_ref = render(T_ref)
    I_src, _ = render(T_src)
    T_src_ref = (torch.linalg.inv(T_src[0]) @ T_ref[0]).numpy()
    return I_ref, I_src, d_ref, T_src_ref


def perturbed(T_src_ref, xi):
    """Rotation perturbed by so3(omega) on the left, translation shifted by rho (so rho = 0 leaves it exact)."""
    T = np.array(T_src_ref, dtype=np.float64, copy=True)
    R = se3_exp(torch.tensor([0.0, 0.0, 0.0] + list(xi[3:]), dtype=torch.float64)).numpy()[:3, :3]
    T[:3, :3] = R @ T[:3, :3]
    T[:3, 3] += np.asarray(xi[:3])
    return T


PERTURBATIONS = [
    ('translation', [0.04, -0.03, 0.05, 0.0, 0.0, 0.0]),
    ('rotation', [0.0, 0.0, 0.0, 0.015, -0.02, 0.01]),
    ('both', [0.03, -0.02, 0.04, 0.01, -0.015, 0.008]),
]


@pytest.mark.parametrize('name,xi', PERTURBATIONS)
def test_alignment_recovers_known_perturbation(pair, name, xi):
    I_ref, I_src, d_ref, T_gt = pair
    T0 = perturbed(T_gt, xi)
    t0, r0 = pose_error(T_gt, T0)
    res = align_photometric(I_ref, I_src, d_ref, K_NP, T0)
    t1, r1 = pose_error(T_gt, res.T_src_ref_44)
    assert res.converged, res.reason
    assert res.reason is None
    # error reduced by more than 10x in both translation and rotation (when perturbed)
    assert (t1 < t0 / 10.0) if t0 > 1e-9 else (t1 < 2e-3)
    assert (r1 < r0 / 10.0) if r0 > 1e-9 else (r1 < 0.05)
    assert res.num_valid > 500      # about a quarter of the 80x60 pixels are selected (max_pixels)
    assert res.residual_ratio < 0.2


def test_alignment_robust_to_outlier_pixels(pair):
    """20 % of the source pixels replaced by uniform noise: still > 10x error reduction."""
    I_ref, I_src, d_ref, T_gt = pair
    g = torch.Generator().manual_seed(0)
    bad = torch.rand(I_src.shape, generator=g) < 0.2
    corrupted = torch.where(bad, torch.rand(I_src.shape, generator=g), I_src)
    T0 = perturbed(T_gt, PERTURBATIONS[2][1])
    t0, r0 = pose_error(T_gt, T0)
    res = align_photometric(I_ref, corrupted, d_ref, K_NP, T0)
    t1, r1 = pose_error(T_gt, res.T_src_ref_44)
    assert res.converged, res.reason
    assert t1 < t0 / 10.0 and r1 < r0 / 10.0


def test_alignment_estimates_exposure_change(pair):
    I_ref, I_src, d_ref, T_gt = pair
    T0 = perturbed(T_gt, PERTURBATIONS[2][1])
    t0, r0 = pose_error(T_gt, T0)
    res = align_photometric(I_ref, 0.8 * I_src + 0.1, d_ref, K_NP, T0)
    t1, r1 = pose_error(T_gt, res.T_src_ref_44)
    assert res.converged, res.reason
    assert t1 < t0 / 10.0 and r1 < r0 / 10.0
    a, b = res.brightness
    # I_ref ~ a I_src' + b with I_src' = 0.8 I_src + 0.1  ->  a = 1.25, b = -0.125 (the prior pulls slightly)
    assert abs(a - 1.25) < 0.05 and abs(b + 0.125) < 0.03
    # without the brightness model the exposure change is a large residual
    fixed = align_photometric(I_ref, 0.8 * I_src + 0.1, d_ref, K_NP, T0,
                              config=AlignmentConfig(affine_brightness=False))
    assert fixed.residual_ratio > 2 * res.residual_ratio


def test_alignment_uses_confidence_and_quarter_resolution_depth(pair):
    """Depth given on a 4x coarser grid (the filter's volume) with a confidence map that zeroes a wrong
    region: the wrong depth must not pull the pose away."""
    I_ref, I_src, d_ref, T_gt = pair
    d_q = torch.nn.functional.avg_pool2d(d_ref[None, None], 4)[0, 0]
    wrong = d_q.clone()
    wrong[:, : d_q.shape[1] // 3] *= 1.6            # a third of the depth map is badly wrong
    conf = torch.ones_like(d_q)
    conf[:, : d_q.shape[1] // 3] = 0.0
    K_q = np.array(K_NP)
    K_q[:2] *= 0.25
    K_q[0, 2] = (K_NP[0, 2] + 0.5) * 0.25 - 0.5
    K_q[1, 2] = (K_NP[1, 2] + 0.5) * 0.25 - 0.5
    T0 = perturbed(T_gt, PERTURBATIONS[2][1])
    t0, r0 = pose_error(T_gt, T0)
    res = align_photometric(I_ref, I_src, wrong, K_NP, T0, conf_ref=conf, K_depth_33=K_q)
    t1, r1 = pose_error(T_gt, res.T_src_ref_44)
    assert res.converged, res.reason
    assert t1 < t0 / 5.0 and r1 < r0 / 5.0


def test_covariance_symmetric_positive_definite_and_gtsam_order(pair):
    I_ref, I_src, d_ref, T_gt = pair
    res = align_photometric(I_ref, I_src, d_ref, K_NP, perturbed(T_gt, PERTURBATIONS[2][1]))
    C = res.covariance_66
    assert C.shape == (6, 6)
    assert np.allclose(C, C.T)
    assert np.all(np.linalg.eigvalsh(C) > 0)
    G = res.between_covariance_gtsam()
    assert np.allclose(G[:3, :3], C[3:, 3:]) and np.allclose(G[3:, 3:], C[:3, :3])
    assert np.allclose(G[:3, 3:], C[3:, :3])
    assert np.allclose(twist_to_gtsam_order(np.diag(np.arange(6.0))), np.diag([3.0, 4, 5, 0, 1, 2]))
    # gtsam accepts it as a Gaussian noise model
    gtsam.noiseModel.Gaussian.Covariance(G)


def test_covariance_matches_the_errors_of_noisy_alignments(pair):
    """Normalised estimation error squared (NEES) against the chi-square bounds: 24 alignments of the pair, each
    with its own i.i.d. Gaussian pixel noise (0.02) on both images and one of the known initial perturbations.
    With ``covariance_inflation=1`` the covariance is the i.i.d. one, so e^T C^-1 e (e = log of the estimated pose
    times the inverse of the true one, the solver's left twist (rho, omega)) is chi-square with 6 degrees of
    freedom and its mean over 24 trials lies in [chi2_0.005(144), chi2_0.995(144)] / 24 = [4.3, 8.0]. The upper end
    gets a factor 1.5: robust weights and the noisy gradients make the solver somewhat over-confident (measured mean
    6.7-8.1). A covariance 10x too large gives a mean near 0.7, 10x too small near 70."""
    from scipy.stats import chi2
    I_ref, I_src, d_ref, T_gt = pair
    T_gt = np.asarray(T_gt, dtype=np.float64)
    gen = torch.Generator().manual_seed(0)
    n, sigma = 24, 0.02
    nees = []
    for i in range(n):
        a = I_ref + sigma * torch.randn(I_ref.shape, generator=gen)
        b = I_src + sigma * torch.randn(I_src.shape, generator=gen)
        T0 = perturbed(T_gt, PERTURBATIONS[i % 3][1])
        res = align_photometric(a, b, d_ref, K_NP, T0, config=AlignmentConfig(covariance_inflation=1.0))
        assert res.converged, res.reason
        w_r = gtsam.Pose3.Logmap(gtsam.Pose3(res.T_src_ref_44 @ np.linalg.inv(T_gt)))   # (omega, rho)
        e = np.concatenate([w_r[3:], w_r[:3]])
        nees.append(float(e @ np.linalg.solve(res.covariance_66, e)))
    lo, hi = chi2.ppf(0.005, 6 * n) / n, chi2.ppf(0.995, 6 * n) / n
    assert lo <= np.mean(nees) <= 1.5 * hi, (np.mean(nees), lo, hi, np.round(nees, 1))
    # the shipped inflation (20) is conservative by that factor, not by another order of magnitude
    assert AlignmentConfig().covariance_inflation == pytest.approx(20.0)


def test_random_images_do_not_converge():
    g = torch.Generator().manual_seed(1)
    a = torch.rand(H, W, generator=g)
    b = torch.rand(H, W, generator=g)
    depth = torch.full((H, W), 2.0)
    res = align_photometric(a, b, depth, K_NP, np.eye(4))
    assert not res.converged
    assert res.reason is not None and 'residual' in res.reason


def test_too_few_valid_pixels(pair):
    I_ref, I_src, d_ref, T_gt = pair
    d = torch.zeros_like(d_ref)
    d[:3, :3] = 2.0
    res = align_photometric(I_ref, I_src, d, K_NP, T_gt)
    assert not res.converged and 'too few' in res.reason


def test_sparse_sampling_matches_warp_image_with_depth(pair):
    """The alignment samples the source only at its selected pixels; that must be exactly the geometry module's
    dense warp at those pixels (values and validity)."""
    from dpv_sensor.core.photometric import _sample_source
    I_ref, I_src, d_ref, T_gt = pair
    depth = d_ref.clone()
    depth[10:20, 30:40] = 0.0                                            # some pixels without depth
    src = torch.stack([I_src, I_src ** 2])[None]
    T = torch.as_tensor(T_gt, dtype=torch.float32)
    Kf = torch.as_tensor(K_NP, dtype=torch.float32)
    dense, valid = warp_image_with_depth(src, depth[None], Kf[None], Kf[None], T[None])
    has = (depth > 0).reshape(-1)
    X_ref = backproject(depth[None], Kf[None])[0].reshape(3, -1)[:, has]
    samples, ok, _ = _sample_source(src, X_ref, Kf, T)
    assert torch.equal(ok, valid.reshape(-1)[has])
    assert 0.3 * has.sum() < ok.sum() < has.sum()                        # some land outside the source
    assert torch.allclose(samples[:, ok], dense.reshape(2, -1)[:, has][:, ok], atol=1e-6)


def test_resample_map_follows_the_camera_model():
    """A map that is a function of the viewing ray keeps that function when moved between grids of the same
    camera with different scale and offset (e.g. the network's stride-4 DPV grid, cx' = cx / 4)."""
    K_full = torch.tensor([[100.0, 0.0, 39.5], [0.0, 100.0, 29.5], [0.0, 0.0, 1.0]], dtype=torch.float64)
    K_q = K_full.clone()
    K_q[:2] /= 4.0                                   # cx/4: not the resize convention
    hq, wq = 15, 20
    v, u = torch.meshgrid(torch.arange(hq, dtype=torch.float64), torch.arange(wq, dtype=torch.float64), indexing='ij')
    ray_x = (u - K_q[0, 2]) / K_q[0, 0]
    ray_y = (v - K_q[1, 2]) / K_q[1, 1]
    maps = torch.stack([1.0 + ray_x, 2.0 + ray_y]).float()
    valid = torch.ones(hq, wq, dtype=torch.bool)
    valid[0, 0] = False
    out, ok = resample_map(maps, valid, K_q, K_full, (H, W))
    V, U = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing='ij')
    want_x = 1.0 + (U - K_full[0, 2]) / K_full[0, 0]
    want_y = 2.0 + (V - K_full[1, 2]) / K_full[1, 1]
    inner = ok.clone()
    inner[:6, :6] = False                              # near the invalid source pixel the average is one-sided
    inner[:2] = inner[-4:] = False
    inner[:, :2] = inner[:, -4:] = False               # beyond the coarse grid's last pixel centre
    assert inner.sum() > 0.7 * H * W
    assert torch.allclose(out[0][inner].double(), want_x[inner], atol=1e-4)
    assert torch.allclose(out[1][inner].double(), want_y[inner], atol=1e-4)
    assert not bool(ok[0, 0])


def test_inverse_depth_std_from_confidence():
    planes = torch.tensor(1.0) / torch.linspace(1 / 0.5, 1 / 10.0, 32)
    spacing = (1 / 0.5 - 1 / 10.0) / 31
    conf = torch.tensor([1.0, 0.6, 0.2, 0.05, 0.0])
    s = inverse_depth_std_from_confidence(conf, planes)
    assert torch.all(s[1:] >= s[:-1])                                  # less confident -> wider
    # conf 0.6 = erf(1.5 / (s sqrt 2)) for s = 1.5 / (sqrt 2 * erfinv(0.6)) = 1.776 planes
    assert abs(float(s[1]) / spacing - 1.5 / (math.sqrt(2) * 0.595116)) < 1e-3
    assert abs(float(s[0]) - 0.5 * spacing) < 1e-6                      # confident: half a plane
    assert abs(float(s[-1]) - 32 / math.sqrt(12) * spacing) < 1e-5       # capped at a uniform DPV


def test_depth_uncertainty_widens_the_covariance(pair):
    I_ref, I_src, d_ref, T_gt = pair
    T0 = perturbed(T_gt, PERTURBATIONS[2][1])
    sharp = align_photometric(I_ref, I_src, d_ref, K_NP, T0, inv_depth_std_ref=torch.full_like(d_ref, 1e-4))
    vague = align_photometric(I_ref, I_src, d_ref, K_NP, T0, inv_depth_std_ref=torch.full_like(d_ref, 0.2))
    assert sharp.converged and vague.converged
    # translation is what depth uncertainty makes uncertain
    assert np.trace(vague.covariance_66[:3, :3]) > 2.0 * np.trace(sharp.covariance_66[:3, :3])
    # and the scale / structure widening of the between factor acts on the translation block only
    G0 = sharp.between_covariance_gtsam()
    G1 = sharp.between_covariance_gtsam(depth_scale_sigma=0.2, translation_sigma_rel=0.5)
    assert np.allclose(G0[:3, :3], G1[:3, :3]) and np.all(np.diag(G1)[3:] > np.diag(G0)[3:])


# ------------------------------------------------------------------------------------------------------------------
# the gtsam window

def run_window(refiner, gt, noisy, imgs, depths, window=5):
    latest = {}
    results = []
    for i in range(len(gt)):
        kfs = [WindowKeyframe(j, imgs[j], K_NP, noisy[j]) for j in range(max(0, i - window + 1), i + 1)]
        res = refiner.refine(kfs[-1], kfs[:-1], depths[i] if i > 0 else None)
        latest.update(res.T_world_cam)
        results.append(res)
    return [latest[j] for j in range(len(gt))], results


@pytest.fixture(scope='module')
def sequence():
    traj = trajectory(6)
    frames = [render(T) for T in traj]
    gt = [T[0].numpy() for T in traj]
    return gt, [f[0] for f in frames], [f[1] for f in frames]


def test_window_refinement_halves_relative_pose_error(sequence):
    gt, imgs, depths = sequence
    noisy = corrupt_trajectory(gt, trans_noise_rel=0.03, rot_noise_deg=0.5, seed=3)
    # exact depth here: no widening of the photometric translation for depth errors
    refiner = WindowPoseRefiner(PoseRefinerConfig.photometric(
        alignment=AlignmentConfig(finest_level=0), depth_scale_sigma=0.0, translation_sigma_rel=0.0,
        inv_depth_offset_sigma=0.0))
    est, results = run_window(refiner, gt, noisy, imgs, depths)
    assert all(r.tracking_ok for r in results), [r.reason for r in results]
    assert not results[0].refined and all(r.refined for r in results[1:])
    t_noisy, r_noisy = relative_pose_errors(noisy, gt)
    t_ref, r_ref = relative_pose_errors(est, gt)
    assert t_ref.mean() <= 0.5 * t_noisy.mean()
    assert r_ref.mean() <= 0.5 * r_noisy.mean()
    # the solved graph's factors: the gauge on one keyframe, odometry between neighbours, an alignment of the
    # reference to each of its max_sources nearest sources; no factor names a keyframe outside the window
    last = results[-1]
    window = sorted(last.T_world_cam)
    assert last.factors['odometry'] == list(zip(window[:-1], window[1:]))
    assert len(last.factors['prior']) == 1 and last.factors['prior'][0][0] in window
    ref = len(gt) - 1
    nearest = sorted(set(window) - {ref}, key=lambda k: abs(k - ref))[:refiner.config.max_sources]
    assert {s for r, s in last.factors['photometric'] if r == ref} == set(nearest)
    assert all(a in window and b in window for k in last.factors for a, b in last.factors[k])
    assert results[0].factors == {}                       # nothing solved without a depth
    # the relative poses handed to the plane sweep are consistent with the refined world poses
    assert np.allclose(last.T_src_ref[0], np.linalg.inv(last.T_world_cam[0 + len(gt) - 5]) @ last.T_world_ref_44)


def test_depth_error_sensitivities_match_realigning_with_a_wrong_depth(pair):
    """The analytic sensitivities of the solution to a depth scale / inverse-depth offset error agree with
    re-running the alignment on a scaled / offset depth."""
    import gtsam
    I_ref, I_src, d_ref, T_gt = pair
    base = align_photometric(I_ref, I_src, d_ref, K_NP, T_gt)

    def twist(Ta, Tb):                      # xi (rho, omega) with Tb = exp(xi) Ta
        x = gtsam.Pose3.Logmap(gtsam.Pose3(Tb @ np.linalg.inv(Ta)))
        return np.r_[x[3:], x[:3]]
    scaled = align_photometric(I_ref, I_src, d_ref * 1.05, K_NP, T_gt)
    emp_s = twist(base.T_src_ref_44, scaled.T_src_ref_44) / 0.05
    offset = torch.where(d_ref > 0, 1.0 / (1.0 / d_ref.clamp_min(1e-6) + 0.02), torch.zeros_like(d_ref))
    shifted = align_photometric(I_ref, I_src, offset, K_NP, T_gt)
    emp_c = twist(base.T_src_ref_44, shifted.T_src_ref_44) / 0.02
    for analytic, empirical in ((base.depth_scale_sensitivity, emp_s), (base.depth_offset_sensitivity, emp_c)):
        assert np.linalg.norm(analytic - empirical) < 0.15 * np.linalg.norm(empirical)
    # a depth scale moves the translation along itself (monocular scale ambiguity), not the rotation
    t = T_gt[:3, 3]
    assert np.allclose(base.depth_scale_sensitivity[:3], t, atol=0.1 * np.linalg.norm(t))
    assert np.linalg.norm(base.depth_scale_sensitivity[3:]) < 0.01
    # an inverse-depth offset moves the rotation
    assert np.linalg.norm(base.depth_offset_sensitivity[3:]) > 0.05


def test_window_without_depth_keeps_odometry(sequence):
    gt, imgs, depths = sequence
    refiner = WindowPoseRefiner(PoseRefinerConfig.photometric())
    kfs = [WindowKeyframe(j, imgs[j], K_NP, gt[j]) for j in range(3)]
    res = refiner.refine(kfs[-1], kfs[:-1], None)
    assert res.tracking_ok and not res.refined and res.reason is None
    for j in range(3):
        assert np.allclose(res.T_world_cam[j], gt[j])


def test_nonconverging_alignment_flags_tracking_loss(sequence):
    gt, imgs, depths = sequence
    refiner = WindowPoseRefiner(PoseRefinerConfig.photometric())
    g = torch.Generator().manual_seed(2)
    noise = [torch.rand(H, W, generator=g) for _ in range(3)]
    kfs = [WindowKeyframe(j, noise[j], K_NP, gt[j]) for j in range(3)]
    res = refiner.refine(kfs[-1], kfs[:-1], depths[2])
    assert not res.tracking_ok and refiner.tracking_lost
    assert 'alignment' in res.reason and 'residual' in res.reason
    assert not res.refined
    # never a diverged pose: the odometry poses come back
    for j in range(3):
        assert np.allclose(res.T_world_cam[j], gt[j])


def test_pose_jump_flags_tracking_loss(sequence):
    """Odometry that claims the camera stood still while it moved 10 cm: the (good) alignment pulls the pose
    further from the odometry than the jump limit allows."""
    gt, imgs, depths = sequence
    cfg = PoseRefinerConfig.photometric(max_jump_translation_m=0.03, alignment=AlignmentConfig(finest_level=0))
    refiner = WindowPoseRefiner(cfg)
    odom = [gt[0], gt[0].copy()]
    kfs = [WindowKeyframe(0, imgs[0], K_NP, odom[0]), WindowKeyframe(2, imgs[2], K_NP, odom[1])]
    res = refiner.refine(kfs[1], kfs[:1], depths[2])
    assert not res.tracking_ok
    assert 'jump' in res.reason
    assert np.allclose(res.T_world_cam[2], odom[1])


def test_estimator_hook_interface(sequence):
    """The refiner is callable with the estimator's PoseRefinementRequest (duck-typed here)."""
    gt, imgs, depths = sequence
    noisy = corrupt_trajectory(gt, trans_noise_rel=0.03, rot_noise_deg=0.5, seed=4)
    refiner = WindowPoseRefiner(PoseRefinerConfig.photometric())

    def kf(j):
        return SimpleNamespace(stamp=0.1 * j, index=j, image_b3hw=imgs[j].expand(3, H, W)[None],
                               K_b33=torch.as_tensor(K_NP, dtype=torch.float32)[None],
                               T_world_cam_44=noisy[j], odom_T_world_cam_44=noisy[j])
    req = SimpleNamespace(keyframes=[kf(0), kf(1), kf(2)], reference=2, depth_hw=depths[2], confidence_hw=None,
                          K_depth_33=None, depths_d=None)
    out = refiner(req)
    assert len(out) == 3 and all(T.shape == (4, 4) for T in out)
    assert refiner.last_result.tracking_ok and refiner.last_result.refined
    te_before = pose_error(np.linalg.inv(gt[1]) @ gt[2], np.linalg.inv(noisy[1]) @ noisy[2])
    te_after = pose_error(np.linalg.inv(gt[1]) @ gt[2], np.linalg.inv(out[1]) @ out[2])
    assert te_after[1] < 0.5 * te_before[1]


# ------------------------------------------------------------------------------------------------------------------
# visual odometry

def test_visual_odometry_with_depth_prior_tracks(sequence):
    gt, imgs, depths = sequence
    depth_of = {id(imgs[j]): depths[j] for j in range(len(imgs))}
    vo = VisualOdometry(VisualOdometryConfig(alignment=AlignmentConfig(finest_level=0)),
                        depth_prior=lambda image, K: (depth_of[id(image)], None))
    poses = []
    for j in range(4):
        r = vo.track(imgs[j], K_NP, 0.1 * j)
        assert r.tracking_ok, r.reason
        poses.append(r.T_world_cam_44)
    assert poses and np.allclose(poses[0], np.eye(4))
    gt_rel = [np.linalg.inv(gt[0]) @ T for T in gt[:4]]       # VO's world = first camera
    for P, G in zip(poses[1:], gt_rel[1:]):
        te, re = pose_error(G, P)
        assert te < 0.01 and re < 0.1


def test_visual_odometry_loses_tracking_and_rebootstraps(sequence):
    gt, imgs, depths = sequence
    vo = VisualOdometry(VisualOdometryConfig(alignment=AlignmentConfig(finest_level=0)))
    assert vo.track(imgs[0], K_NP, 0.0).reason == 'bootstrap'
    noise = torch.rand(H, W, generator=torch.Generator().manual_seed(5))
    lost = vo.track(noise, K_NP, 0.1)
    assert not lost.tracking_ok and 'alignment failed' in lost.reason
    again = vo.track(imgs[1], K_NP, 0.2)
    assert again.tracking_ok and again.bootstrap
    # after a keyframe with the filter's depth is set, frames track against it
    vo.set_keyframe(imgs[1], K_NP, again.T_world_cam_44, depths[1], stamp=0.2)
    assert vo.has_keyframe_depth
    nxt = vo.track(imgs[2], K_NP, 0.3)
    assert nxt.tracking_ok and not nxt.bootstrap
    rel_est = np.linalg.inv(again.T_world_cam_44) @ nxt.T_world_cam_44
    te, re = pose_error(np.linalg.inv(gt[1]) @ gt[2], rel_est)
    assert te < 0.01 and re < 0.1


def test_visual_odometry_caps_its_working_resolution():
    """Frames wider than max_width are tracked on a coarser pyramid level (the node hands VO full frames)."""
    vo = VisualOdometry(VisualOdometryConfig(max_width=40, alignment=AlignmentConfig(finest_level=0)))
    cfg = vo._config_for(np.zeros((60, 80, 3), np.uint8))
    assert cfg.finest_level == 1 and cfg.num_levels == AlignmentConfig().num_levels + 1
    assert vo._config_for(torch.zeros(3, 60, 80)).finest_level == 1
    assert vo._config_for(np.zeros((30, 40))).finest_level == 0


def test_corrupt_trajectory_has_the_requested_per_keyframe_errors():
    gt = [T[0].numpy() for T in trajectory(8)]
    noisy = corrupt_trajectory(gt, trans_noise_rel=0.03, rot_noise_deg=0.5, seed=7)
    assert np.allclose(noisy[0], gt[0])
    t_err, r_err = relative_pose_errors(noisy, gt)
    steps = np.array([np.linalg.norm((np.linalg.inv(gt[i - 1]) @ gt[i])[:3, 3]) for i in range(1, 8)])
    assert np.allclose(r_err, 0.5, atol=1e-6)                    # 0.5 deg about a random axis, every keyframe
    assert np.allclose(t_err, 0.03 * steps, rtol=1e-6)           # 3 % of the step, random direction
    biased = corrupt_trajectory(gt, trans_noise_rel=0.0, rot_noise_deg=0.0, scale_bias=0.1, seed=7)
    assert np.allclose(relative_pose_errors(biased, gt)[0], 0.1 * steps, rtol=1e-6)


class _Seq:
    """The part of a dpv_sensor.data.sequence.Sequence that studies.poses.gt_consistency reads."""

    def __init__(self, poses, imgs, depths):
        self.K, self._poses, self._imgs, self._depths = K_NP, poses, imgs, depths

    def __len__(self):
        return len(self._poses)

    def pose(self, i):
        return self._poses[i]

    def image(self, i):
        return self._imgs[i]

    def depth(self, i):
        return self._depths[i].numpy()


def test_gt_consistency_check_finds_a_wrong_ground_truth_pose(sequence):
    from dpv_sensor.studies.poses import gt_consistency
    gt, imgs, depths = sequence
    exact = gt_consistency('exact', _Seq(gt, imgs, depths))
    assert exact['pairs'] == len(gt) - 1
    assert exact['moved_deg'] < 0.1 and exact['photo_aligned'] <= exact['photo_gt'] + 1e-3
    # a "ground truth" whose poses are off by 0.6 deg: the alignment moves back by about that and the photometric
    # error drops
    wrong = [T @ se3(rot_y(math.radians(0.6 * (-1) ** i)))[0].numpy() for i, T in enumerate(gt)]
    bad = gt_consistency('wrong', _Seq(wrong, imgs, depths))
    assert bad['moved_deg'] > 0.8 and bad['photo_aligned'] < 0.7 * bad['photo_gt']


def _rot_pose(yaw_deg=0.0, x=0.0):
    T = np.eye(4)
    a = math.radians(yaw_deg)
    T[:3, :3] = [[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]]
    T[0, 3] = x
    return T


@pytest.mark.parametrize('yaw,x,skipped', [(5.0, 0.005, True),      # 0.087 rad vs 0.0025 parallax: ratio 35
                                          (1.0, 0.05, False)])      # 0.017 rad vs 0.025: ratio 0.7
def test_turning_in_place_keeps_the_odometry(yaw, x, skipped):
    """A window whose camera turns in place (rotation > 8x the parallax of the baseline at the predicted depth) is
    not aligned: the odometry poses come back unchanged, tracking stays ok, and the result says why."""
    rng = np.random.default_rng(0)
    K = np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]])
    img = rng.random((48, 64, 3)).astype(np.float32)
    ref = WindowKeyframe(1.0, img, K, _rot_pose(yaw, x))
    src = WindowKeyframe(0.0, img, K, _rot_pose())
    refiner = WindowPoseRefiner(PoseRefinerConfig.photometric(max_sources=1))
    init = {0.0: src.T_world_cam_odom_44, 1.0: ref.T_world_cam_odom_44}
    why = refiner._turning_in_place(ref, [src], init, np.full((12, 16), 2.0))
    assert (why is not None) == skipped
    if skipped:
        assert why.startswith('turning in place: 5.0 deg') and '> 8' in why
        res = refiner.refine(ref, [src], np.full((48, 64), 2.0), np.ones((48, 64)))
        assert res.tracking_ok and not res.refined and res.skipped == why
        np.testing.assert_allclose(res.T_world_ref_44, ref.T_world_cam_odom_44, atol=1e-12)
        assert all(a is None for a in res.alignments)
    assert WindowPoseRefiner(PoseRefinerConfig(max_rotation_parallax=0.0))._turning_in_place(
        ref, [src], init, np.full((12, 16), 2.0)) is None


def test_the_window_reports_where_its_odometry_covariance_comes_from():
    from dpv_sensor.stream.window_graph import DRIFT, FIXED, PUBLISHED, odometry_steps
    from dpv_sensor.core import pose_uncertainty
    cfg = PoseRefinerConfig(odom_covariance='odometry',
                            drift=pose_uncertainty.DriftModel(0.02, 1.0, 0.02, 0.0, cov_trans_per_m=0.02))
    odom = {k: np.eye(4) + np.pad(np.array([[0.1 * k], [0.0], [0.0]]), ((0, 1), (3, 0))) for k in range(3)}  # 10 cm
    keys = [0, 1, 2]
    drift = odometry_steps(keys, odom, {k: None for k in keys}, cfg)
    assert drift.source == DRIFT
    assert math.degrees(drift.rot_rad) == pytest.approx(0.1 / math.sqrt(3), rel=1e-6)     # 1 deg/m over 0.1 m
    assert drift.trans_m == pytest.approx(0.002 / math.sqrt(3), rel=1e-6)                  # 2 % of 0.1 m
    # a covariance that grows by (1 mm)^2 and (0.05 deg)^2 per axis per step
    cov = {k: np.diag([(1e-3) ** 2 * (k + 1)] * 3 + [math.radians(0.05) ** 2 * (k + 1)] * 3) for k in keys}
    published = odometry_steps(keys, odom, cov, cfg)
    assert published.source == PUBLISHED
    assert math.degrees(published.rot_rad) == pytest.approx(0.05, rel=1e-6)
    assert published.trans_m == pytest.approx(1e-3, rel=1e-6)
    fixed = odometry_steps(keys, odom, cov, PoseRefinerConfig.photometric())
    assert fixed.source == FIXED
    assert math.degrees(fixed.rot_rad) == pytest.approx(PoseRefinerConfig().odom_sigma_rot_deg)
    assert odometry_steps([0], odom, cov, cfg) is None


def test_alignment_depth_perturbations():
    from dpv_sensor.studies.alignment_depth import perturbed_depth
    rng = np.random.default_rng(0)
    d = np.full((64, 80), 2.0, np.float32) + np.linspace(0, 1, 80, dtype=np.float32)
    assert np.array_equal(perturbed_depth(d, 'gt', 0.3, rng), d)
    smooth = perturbed_depth(d, 'smooth', 0.3, rng)
    assert smooth.shape == d.shape and np.all(smooth > 0)
    ratio = np.log(perturbed_depth(d, 'structured', 0.3, rng) / d)
    assert ratio.std() == pytest.approx(0.3, rel=0.05) and abs(ratio.mean()) < 0.3
