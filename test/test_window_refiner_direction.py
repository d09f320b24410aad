"""The window refiner's keypoint factor with ``keypoint_direction='odometry'`` (stream.window_refiner): its rotation
is the keypoint rotation *given* the odometry's translation direction, and its covariance the conditional one,
much tighter than the rotation's marginal where the two are correlated (a turn and a sideways step move the matches
alike). A direction handed over the wrong way round (more than 30 degrees from the keypoints') falls back to the
marginal silently, so only the covariance shows it.

The two views are built by hand (no rendering, no detector): 150 points 2-4 m in front of a 250 px camera
(320x240), seen again after a step of (0.1, 0, 0.05) m and a turn of (0.5, 2, 0.3) degrees, with 0.3 px of noise
on every position and the same random SIFT-like descriptor in both views, so every point matches itself.
"""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

import dpv_sensor.stream.window_refiner as WR
from dpv_sensor.core.keypoint_pose import (Features, KeypointConfig, keypoint_relative_pose,
                                           rotation_factor_covariance_gtsam, rotation_given_direction_gain)
from dpv_sensor.stream.window_refiner import PoseRefinerConfig, WindowKeyframe, WindowPoseRefiner

F_PX = 250.0
K = np.array([[F_PX, 0.0, 159.5], [0.0, F_PX, 119.5], [0.0, 0.0, 1.0]])
R_B_A = cv2.Rodrigues(np.radians([0.5, 2.0, 0.3]).reshape(3, 1))[0]
T_DIR = np.array([0.1, 0.0, 0.05])


def _two_views():
    """(Features of view a, of view b, T_b_a): the scene of the module doc."""
    rng = np.random.default_rng(3)
    n = 150
    uv = np.c_[rng.uniform(10, 310, n), rng.uniform(10, 230, n)]
    z = rng.uniform(2.0, 4.0, n)
    X_a = (np.c_[uv, np.ones(n)] @ np.linalg.inv(K).T) * z[:, None]
    X_b = X_a @ R_B_A.T + T_DIR
    p_b = X_b @ K.T
    p_b = p_b[:, :2] / p_b[:, 2:]
    p_a = uv + rng.normal(0.0, 0.3, uv.shape)
    p_b = p_b + rng.normal(0.0, 0.3, p_b.shape)
    desc = rng.integers(0, 256, (n, 128)).astype(np.float32)

    def features(p):
        return Features(tuple(cv2.KeyPoint(float(x), float(y), 3.0) for x, y in p), desc.copy(), 'sift')

    T_b_a = np.eye(4)
    T_b_a[:3, :3] = R_B_A
    T_b_a[:3, 3] = T_DIR
    return features(p_a), features(p_b), T_b_a


@pytest.fixture(scope='module')
def views():
    return _two_views()


def _stds_deg(cov_33):
    """The rotation's stds (degrees) along its principal axes, smallest first."""
    return np.degrees(np.sqrt(np.linalg.eigvalsh(0.5 * (cov_33 + cov_33.T))))


def _config(direction):
    return PoseRefinerConfig(keypoint_factors=True, keypoint_direction=direction, rotation_evidence='keypoints',
                             odom_covariance='odometry', marginals=True)


def _odometry_cov(rot_deg, trans_m):
    return np.diag([trans_m ** 2] * 3 + [math.radians(rot_deg) ** 2] * 3)


def test_the_hand_built_pair_has_a_marginal_much_wider_than_its_conditional(views):
    """The case itself: the keypoints see the motion, and knowing the direction halves the widest rotation std."""
    fa, fb, T_b_a = views
    kp = keypoint_relative_pose(fa, fb, K, KeypointConfig())
    assert kp.ok and kp.inliers >= 100, kp.reason
    assert float(kp.t_dir_b @ T_DIR) / np.linalg.norm(T_DIR) > math.cos(math.radians(5.0))
    marginal = _stds_deg(kp.rotation_covariance())
    conditional = _stds_deg(rotation_given_direction_gain(kp.cov_55)[1])
    assert marginal[-1] > 0.25 and conditional[-1] < 0.2, (marginal, conditional)


def test_the_odometry_direction_factor_carries_the_conditional_rotation_covariance(views, monkeypatch):
    """The factor _keypoint_factors hands to the graph for T_src_ref: its rotation block is the conditional
    covariance (to rounding), the widest std under 0.2 degrees where the marginal's is over 0.25, and its
    translation the odometry's, left free (10 m std)."""
    fa, fb, T_b_a = views
    refiner = WindowPoseRefiner(_config('odometry'))
    monkeypatch.setattr(refiner, '_keypoints', lambda f: {0: fa, 1: fb}[f.key])
    T_world_ref, T_world_src = np.eye(4), np.linalg.inv(T_b_a)        # exact odometry: T_src_ref = T_b_a
    ref = WindowKeyframe(0, None, K, T_world_ref)
    src = WindowKeyframe(1, None, K, T_world_src)
    factors, (kp,) = refiner._keypoint_factors(ref, [src], {0: T_world_ref, 1: T_world_src})
    ((s, r, T, cov),) = factors
    assert (s, r) == (1, 0) and kp.ok
    R = kp.R_b_a
    cov_rot_b = R @ cov[:3, :3] @ R.T                 # back from gtsam's tangent (frame a) to frame b's axes
    stds = _stds_deg(cov_rot_b)
    assert stds[-1] < 0.2, stds
    assert stds[-1] < 0.6 * _stds_deg(kp.rotation_covariance())[-1]
    assert not np.allclose(cov_rot_b, kp.rotation_covariance(), rtol=0.1)
    conditional = rotation_given_direction_gain(kp.cov_55)[1]
    np.testing.assert_allclose(cov, rotation_factor_covariance_gtsam(conditional, kp.R_b_a, 100.0), rtol=1e-9,
                               atol=1e-15)
    np.testing.assert_allclose(T[:3, 3], T_DIR, atol=1e-12)
    np.testing.assert_allclose(np.diag(cov[3:, 3:]), [100.0] * 3, rtol=1e-9)
    err_deg = math.degrees(np.linalg.norm(cv2.Rodrigues(T[:3, :3] @ R_B_A.T)[0]))
    assert err_deg < 0.3


def test_the_refined_source_is_as_sure_as_the_conditional_rotation(views, monkeypatch):
    """Through refine(): an odometry that admits 2 degrees per axis, the keypoints' factor the only other
    evidence: the source's marginal rotation std follows the factor's (under 0.12 degrees with the conditional;
    the marginal's factor would leave it near 0.2)."""
    fa, fb, T_b_a = views
    monkeypatch.setattr(WR, 'detect_features', lambda image, cfg=None: {'a': fa, 'b': fb}[image])
    ref = WindowKeyframe(0, 'a', K, np.eye(4), _odometry_cov(0.001, 1e-4))
    src = WindowKeyframe(1, 'b', K, np.linalg.inv(T_b_a), _odometry_cov(0.001, 1e-4) + _odometry_cov(2.0, 0.005))
    res = WindowPoseRefiner(_config('odometry')).refine(ref, [src])
    assert res.refined and res.gate == 'refined' and res.factors['keypoint'] == [(1, 0)]
    assert math.degrees(res.source_sigma[1].rot_rad) < 0.12, res.source_sigma


@pytest.mark.parametrize('off_deg, conditional', [(0.0, True), (29.0, True), (31.0, False), (180.0, False)])
def test_a_direction_more_than_30_degrees_from_the_keypoints_gives_the_marginal(views, off_deg, conditional):
    fa, fb, _ = views
    kp = keypoint_relative_pose(fa, fb, K, KeypointConfig())
    axis = np.cross(kp.t_dir_b, [0.0, 1.0, 0.0])
    u = cv2.Rodrigues((math.radians(off_deg) * axis / np.linalg.norm(axis)).reshape(3, 1))[0] @ kp.t_dir_b
    R, cov = kp.rotation_given_direction(u)
    if conditional:
        np.testing.assert_allclose(cov, rotation_given_direction_gain(kp.cov_55)[1], rtol=1e-12)
    else:
        np.testing.assert_array_equal(cov, kp.rotation_covariance())
        np.testing.assert_array_equal(R, kp.R_b_a)


def test_the_keypoint_factors_go_to_the_nearest_keypoint_sources_only(views, monkeypatch):
    """keypoint_sources 2 (the default) with three sources: the two nearest the reference by key get a factor, the
    third none."""
    fa, fb, T_b_a = views
    refiner = WindowPoseRefiner(_config('odometry'))
    assert refiner.config.keypoint_sources == 2
    monkeypatch.setattr(refiner, '_keypoints', lambda f: fa if f.key == 0 else fb)
    T_world_src = np.linalg.inv(T_b_a)
    ref = WindowKeyframe(0, None, K, np.eye(4))
    sources = [WindowKeyframe(k, None, K, T_world_src) for k in (3, 1, 2)]
    factors, kps = refiner._keypoint_factors(ref, sources, {0: np.eye(4), 1: T_world_src, 2: T_world_src,
                                                            3: T_world_src})
    assert [(s, r) for s, r, _T, _cov in factors] == [(1, 0), (2, 0)] and len(kps) == 2


def test_the_keypoints_direction_factor_takes_the_odometrys_length(views, monkeypatch):
    """keypoint_direction 'keypoints': the factor's translation is the keypoints' direction scaled to the
    odometry's baseline, |(0.1, 0, 0.05)| = 0.1118 m, along (0.894, 0, 0.447) within the keypoints' few degrees,
    and its covariance is scaled to that baseline too."""
    fa, fb, T_b_a = views
    refiner = WindowPoseRefiner(_config('keypoints'))
    monkeypatch.setattr(refiner, '_keypoints', lambda f: {0: fa, 1: fb}[f.key])
    T_world_src = np.linalg.inv(T_b_a)
    ref, src = WindowKeyframe(0, None, K, np.eye(4)), WindowKeyframe(1, None, K, T_world_src)
    ((s, r, T, cov),), _ = refiner._keypoint_factors(ref, [src], {0: np.eye(4), 1: T_world_src})
    assert np.linalg.norm(T[:3, 3]) == pytest.approx(math.hypot(0.1, 0.05), rel=1e-9)
    assert float(T[:3, 3] @ T_DIR) / np.linalg.norm(T_DIR) ** 2 > math.cos(math.radians(5.0))
    # its length is the odometry's, known to keypoint_scale_sigma_rel (0.5) of it: the widest translation std is
    # 0.5 * 0.1118 = 55.9 mm (across the baseline the keypoints' direction leaves millimetres)
    stds = np.sqrt(np.linalg.eigvalsh(cov[3:, 3:]))
    assert stds[-1] == pytest.approx(0.5 * math.hypot(0.1, 0.05), rel=0.02) and stds[-2] < 0.02, stds
