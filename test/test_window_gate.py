"""The window refiner's pose-error model: keypoint factors, marginals and the gate (stream.window_refiner)."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from dpv_sensor.core.pose_math import rotation_angle_np
from dpv_sensor.core.keypoint_pose import KeypointConfig
from dpv_sensor.stream.window_refiner import PoseRefinerConfig, WindowKeyframe, WindowPoseRefiner

ERR_DEG = 2.0


@pytest.fixture(scope='module')
def pair():
    """Frames 0 and 8 of rendered room 7 (320x240; 7.9 deg, 0.107 m apart): images, K, true world poses."""
    from dpv_sensor.data.synthetic import render_sequence
    seq = render_sequence(seed=7, num_frames=9, width=320, height=240, plain_wall_prob=0.0)
    return seq.image(0), seq.image(8), np.asarray(seq.K, np.float64), seq.pose(0), seq.pose(8)


def _cov(rot_deg: float, trans_m: float) -> np.ndarray:
    """ROS-order pose covariance with per-axis stds rot_deg and trans_m."""
    return np.diag([trans_m ** 2] * 3 + [math.radians(rot_deg) ** 2] * 3)


def _window(pair, src_rot_deg: float, ref_img=None, src_img=None):
    """Source (key 1) with the published covariance src_rot_deg (per axis) and a 2 deg rotation error in its
    odometry; the reference (key 0) exact, with a tiny covariance."""
    img_a, img_b, K, T_wa, T_wb = pair
    T_odom_b = T_wb.copy()
    T_odom_b[:3, :3] = T_wb[:3, :3] @ cv2.Rodrigues(np.radians([ERR_DEG, 0, 0]).reshape(3, 1))[0]
    ref = WindowKeyframe(0, img_a if ref_img is None else ref_img, K, T_wa, _cov(0.001, 1e-4))
    src = WindowKeyframe(1, img_b if src_img is None else src_img, K, T_odom_b,
                         _cov(0.001, 1e-4) + _cov(src_rot_deg, 0.005))
    return ref, src


def _config(max_features=2000, **kw):
    """The SIFT keypoint factors (these tests are about them; the default evidence may be the flow's)."""
    kw.setdefault('rotation_evidence', 'keypoints')
    return PoseRefinerConfig(odom_covariance='odometry', keypoint_factors=True, marginals=True,
                             keypoint=KeypointConfig(max_features=max_features, ratio=0.75), **kw)


def _rot_err(T_est, T_true):
    return math.degrees(rotation_angle_np(T_est[:3, :3].T @ T_true[:3, :3]))


@pytest.mark.parametrize('direction', ['keypoints', 'odometry'])
def test_keypoint_factor_corrects_rotation_and_the_marginal_is_below_the_odometry(pair, direction):
    ref, src = _window(pair, 2.0)
    res = WindowPoseRefiner(_config(keypoint_direction=direction)).refine(ref, [src])
    assert res.refined and res.gate == 'refined'
    assert _rot_err(src.T_world_cam_odom_44, pair[4]) == pytest.approx(ERR_DEG, abs=1e-6)
    assert _rot_err(res.T_world_cam[1], pair[4]) < 0.5
    sig = res.source_sigma[1]
    assert sig.rot_rad < math.radians(2.0)                  # the images told more than the odometry's 2 deg
    assert res.correction[1] > 1.0


def test_the_marginal_grows_when_inliers_drop(pair):
    ref, src = _window(pair, 2.0)
    many = WindowPoseRefiner(_config(2000)).refine(ref, [src])
    few = WindowPoseRefiner(_config(80)).refine(ref, [src])
    assert many.refined and few.refined
    assert few.keypoints[0].inliers < many.keypoints[0].inliers
    assert few.source_sigma[1].rot_rad > many.source_sigma[1].rot_rad


def test_gate_keeps_odometry_on_a_textureless_window(pair):
    flat = np.full((240, 320, 3), 128, np.uint8)
    ref, src = _window(pair, 2.0, flat, flat)
    refiner = WindowPoseRefiner(_config(gate_min_inliers=20))
    res = refiner.refine(ref, [src])
    assert not res.refined and res.gate == 'kept_few_inliers'
    np.testing.assert_array_equal(res.T_world_cam[1], src.T_world_cam_odom_44)
    assert res.source_sigma == {} and res.correction == pytest.approx((0.0, 0.0), abs=1e-9)
    assert refiner.gate_counts == {'kept_few_inliers': 1}


def test_gate_rejects_a_correction_the_odometry_covariance_rules_out(pair):
    # the odometry claims 0.01 deg per axis, the keypoints differ from it by about 2 deg
    ref, src = _window(pair, 0.01)
    refiner = WindowPoseRefiner(_config(gate_chi2=16.27))     # 3 dof (rotation), 99.9 %
    res = refiner.refine(ref, [src])
    assert res.gate == 'rejected_chi2' and not res.refined
    np.testing.assert_array_equal(res.T_world_cam[1], src.T_world_cam_odom_44)
    # the same images with an odometry that admits 2 deg per axis: the correction passes the same gate
    assert refiner.gate_counts == {'rejected_chi2': 1}
    ref, src = _window(pair, 2.0)
    refiner = WindowPoseRefiner(_config(gate_chi2=16.27))
    res = refiner.refine(ref, [src])
    assert res.gate == 'refined' and _rot_err(res.T_world_cam[1], pair[4]) < 0.5
    assert refiner.gate_counts == {'refined': 1}


@pytest.mark.parametrize('sources', [0, 1])
def test_photometric_sources_parameter_sets_the_photometric_factors(pair, sources):
    """refine_photometric_sources: 0 leaves keypoints and odometry (no alignment is run), 1 aligns the nearest."""
    from dpv_sensor import params as P
    from dpv_sensor.data.synthetic import render_sequence
    depth = render_sequence(seed=7, num_frames=1, width=320, height=240, plain_wall_prob=0.0).depth(0)
    values = P.validate(dict(P.defaults(), refine_odom_covariance='odometry', refine_keypoints=True,
                             refine_photometric_sources=sources))
    config = PoseRefinerConfig.from_params(values)
    config.keypoint = KeypointConfig(max_features=2000, ratio=0.75)
    assert config.max_sources == sources
    ref, src = _window(pair, 2.0)
    res = WindowPoseRefiner(config).refine(ref, [src], depth_ref=np.asarray(depth, np.float32))
    assert res.refined and res.factors['keypoint'] == [(1, 0)]
    assert res.factors.get('photometric', []) == ([(0, 1)] if sources else [])
    assert (res.alignments[0] is not None) == bool(sources)
    assert _rot_err(res.T_world_cam[1], pair[4]) < 0.5


def test_a_rotation_only_keypoint_factor_leaves_the_translation_to_the_odometry(pair):
    # the odometry's translation off by 1 cm sideways, its rotation exact: with the direction left to the
    # odometry the refined translation stays the odometry's; with the keypoints' direction it moves (a little:
    # the odometry's covariance is capped at 2 % of the step, the keypoints' direction is 18 deg uncertain here)
    img_a, img_b, K, T_wa, T_wb = pair
    T_odom_b = T_wb.copy()
    T_odom_b[:3, 3] += T_wb[:3, :3] @ np.array([0.01, 0.0, 0.0])
    ref = WindowKeyframe(0, img_a, K, T_wa, _cov(0.001, 1e-4))
    src = WindowKeyframe(1, img_b, K, T_odom_b, _cov(0.001, 1e-4) + _cov(0.5, 0.02))
    moved = {}
    for direction in ('keypoints', 'odometry'):
        res = WindowPoseRefiner(_config(keypoint_direction=direction)).refine(ref, [src])
        assert res.refined
        moved[direction] = float(np.linalg.norm(res.T_world_cam[1][:3, 3] - T_odom_b[:3, 3]))
    assert moved['odometry'] < 1e-6 and moved['keypoints'] > 5e-5


@pytest.mark.parametrize('kind', ['constant pose and twist 1e6', 'pose jumping to 1e6'])
def test_a_huge_odometry_covariance_trusts_the_images_and_refinement_still_corrects(pair, kind):
    # the source's odometry 2 deg off. A constant pose covariance (here 1e6, as ROS 1 diff_drive publishes for
    # unmeasured axes) does not grow, so the twist covariance (1e6 as well) is integrated; a pose covariance that
    # jumps grows by 1e6. Either way the odometry factor is loose, capped at the window's jump limits (never the
    # 0.001 deg / 0.1 mm floor, which would hold the odometry and leave the 2 deg), and the keypoints correct it
    from dpv_sensor.stream.window_graph import PUBLISHED, TWIST
    img_a, img_b, K, T_wa, T_wb = pair
    T_odom_b = T_wb.copy()
    T_odom_b[:3, :3] = T_wb[:3, :3] @ cv2.Rodrigues(np.radians([ERR_DEG, 0, 0]).reshape(3, 1))[0]
    huge = np.eye(6) * 1e6
    if kind.startswith('constant'):
        ref = WindowKeyframe(0, img_a, K, T_wa, huge, huge, stamp=10.0)
        src = WindowKeyframe(1, img_b, K, T_odom_b, huge, huge, stamp=10.3)
    else:
        ref = WindowKeyframe(0, img_a, K, T_wa, _cov(0.001, 1e-4), stamp=10.0)
        src = WindowKeyframe(1, img_b, K, T_odom_b, huge, stamp=10.3)
    cfg = _config(keypoint_direction='odometry', gate_chi2=16.27)
    res = WindowPoseRefiner(cfg).refine(ref, [src])
    assert res.odometry.source == (TWIST if kind.startswith('constant') else PUBLISHED)
    assert (res.odometry.rot_rad, res.odometry.trans_m) == pytest.approx(
        (math.radians(cfg.max_jump_rotation_deg), cfg.max_jump_translation_m))
    assert res.refined and res.gate == 'refined'
    assert _rot_err(res.T_world_cam[1], pair[4]) < 0.5 and res.correction[1] > 1.0


def test_photometric_gate_drops_an_alignment_the_odometry_covariance_rules_out(pair):
    """refine_photometric_gate_chi2: an alignment that moves the source by 2 deg is used where the odometry admits 2
    deg per axis (chi-square about 1) and dropped, alone and counted, where it claims 0.01 deg (about 40000)."""
    from dpv_sensor import params as P
    from dpv_sensor.data.synthetic import render_sequence
    depth = np.asarray(render_sequence(seed=7, num_frames=1, width=320, height=240, plain_wall_prob=0.0).depth(0),
                       np.float32)
    values = P.validate(dict(P.defaults(), refine_keypoints=False, refine_photometric_sources=1,
                             refine_photometric_gate_chi2=16.27))
    config = PoseRefinerConfig.from_params(values)
    assert config.photometric_gate_chi2 == 16.27
    ref, src = _window(pair, 2.0)
    refiner = WindowPoseRefiner(config)
    res = refiner.refine(ref, [src], depth_ref=depth)
    assert res.refined and res.factors['photometric'] == [(0, 1)]
    assert _rot_err(res.T_world_cam[1], pair[4]) < 0.3
    assert refiner.factor_counts == {'photometric_used': 1}
    ref, src = _window(pair, 0.01)
    refiner = WindowPoseRefiner(config)
    res = refiner.refine(ref, [src], depth_ref=depth)
    assert res.tracking_ok and not res.refined and res.alignments[0].converged
    np.testing.assert_array_equal(res.T_world_cam[1], src.T_world_cam_odom_44)
    assert refiner.factor_counts == {'photometric_inconsistent': 1}
    # without the gate the same alignment is used against the odometry's 0.01 deg
    refiner = WindowPoseRefiner(PoseRefinerConfig.from_params(dict(values, refine_photometric_gate_chi2=0.0)))
    res = refiner.refine(ref, [src], depth_ref=depth)
    assert res.refined and refiner.factor_counts == {'photometric_used': 1}
