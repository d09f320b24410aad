"""Keypoint relative pose (core.keypoint_pose): a rendered pair, the covariance's dependence on the inliers, and
images without texture."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from dpv_sensor.core.pose_math import rotation_angle_np
from dpv_sensor.core.keypoint_pose import KeypointConfig, KeypointPose, keypoint_covariance, keypoint_relative_pose


@pytest.fixture(scope='module')
def pair():
    """Frames 0 and 8 of rendered room 7 (320x240; 7.9 deg and 0.107 m apart) and their true T_b_a."""
    from dpv_sensor.data.synthetic import render_sequence
    seq = render_sequence(seed=7, num_frames=9, width=320, height=240, plain_wall_prob=0.0)
    T_b_a = np.linalg.inv(seq.pose(8)) @ seq.pose(0)
    return seq.image(0), seq.image(8), np.asarray(seq.K, np.float64), T_b_a


def _rot_err_deg(R, T_b_a):
    return math.degrees(rotation_angle_np(np.asarray(R).T @ T_b_a[:3, :3]))


def test_keypoints_recover_a_known_rotation_error(pair):
    img_a, img_b, K, T_b_a = pair
    odom = T_b_a.copy()
    odom[:3, :3] = cv2.Rodrigues(np.radians([2.0, 0.0, 0.0]).reshape(3, 1))[0] @ T_b_a[:3, :3]
    assert _rot_err_deg(odom[:3, :3], T_b_a) == pytest.approx(2.0, abs=1e-6)
    res = keypoint_relative_pose(img_a, img_b, K, KeypointConfig(max_features=2000, ratio=0.75))
    assert res.ok, res.reason
    assert res.inliers >= 50
    assert _rot_err_deg(res.R_b_a, T_b_a) < 0.5            # 2 deg of odometry error -> under a quarter of it
    t_true = T_b_a[:3, 3] / np.linalg.norm(T_b_a[:3, 3])
    assert math.degrees(math.acos(float(np.clip(res.t_dir_b @ t_true, -1, 1)))) < 10.0
    cov = res.between_covariance_gtsam(0.1, 0.05)
    assert cov.shape == (6, 6) and np.allclose(cov, cov.T) and np.all(np.linalg.eigvalsh(cov) > 0)
    # along the baseline the translation is the odometry's: its variance is (0.05 * 0.1)^2 plus the direction's
    t_a = res.R_b_a.T @ res.t_dir_b                      # the direction in frame a's axes (gtsam tangent)
    assert float(t_a @ cov[3:, 3:] @ t_a) == pytest.approx(0.005 ** 2, rel=1e-6)


def test_fewer_inliers_give_a_larger_covariance(pair):
    # by hand: 4x fewer inliers double the std; the direction's std scales with 1 / parallax
    s100 = keypoint_covariance(100, 200.0, 10.0)
    s25 = keypoint_covariance(25, 200.0, 10.0)
    assert s100 == pytest.approx((1 / (200 * 10), 1 / (10 * 10)))
    assert s25[0] == pytest.approx(2 * s100[0]) and s25[1] == pytest.approx(2 * s100[1])
    assert keypoint_covariance(0, 200.0, 10.0) == (math.inf, math.inf)
    img_a, img_b, K, _ = pair
    many = keypoint_relative_pose(img_a, img_b, K, KeypointConfig(max_features=2000, ratio=0.75))
    few = keypoint_relative_pose(img_a, img_b, K, KeypointConfig(max_features=80, ratio=0.75))
    assert many.ok and few.ok, (many.reason, few.reason)
    assert few.inliers < many.inliers
    assert np.trace(few.rotation_covariance()) > np.trace(many.rotation_covariance())


def test_textureless_images_give_no_estimate():
    K = np.array([[200.0, 0, 160], [0, 200.0, 120], [0, 0, 1]])
    flat = np.full((240, 320, 3), 128, np.uint8)
    res = keypoint_relative_pose(flat, flat, K)
    assert not res.ok and 'too few keypoints' in res.reason
    assert res.inliers == 0 and math.isinf(res.sigma_rot_rad)


def test_features_detected_once_give_the_same_pose_as_the_images(pair):
    from dpv_sensor.core.keypoint_pose import detect_features
    img_a, img_b, K, _ = pair
    cfg = KeypointConfig(max_features=2000, ratio=0.75)
    from_images = keypoint_relative_pose(img_a, img_b, K, cfg)
    from_features = keypoint_relative_pose(detect_features(img_a, cfg), detect_features(img_b, cfg), K, cfg)
    assert from_images.ok and from_features.ok
    assert from_features.inliers == from_images.inliers
    assert np.array_equal(from_features.R_b_a, from_images.R_b_a)
    with pytest.raises(ValueError, match='orb'):
        keypoint_relative_pose(detect_features(img_a, cfg), img_b, K, KeypointConfig(detector='orb'))


def test_floors_add_to_the_inliers_covariance_in_quadrature(pair):
    img_a, img_b, K, _ = pair
    cfg = KeypointConfig(max_features=2000, ratio=0.75)
    raw = keypoint_relative_pose(img_a, img_b, K, cfg)
    floored = keypoint_relative_pose(img_a, img_b, K, KeypointConfig(max_features=2000, ratio=0.75,
                                                                     rotation_floor_deg=0.5, direction_floor_deg=2.0))
    assert raw.ok and floored.ok and raw.t_dir_b is not None
    np.testing.assert_allclose(floored.R_b_a, raw.R_b_a)           # the estimate is the same, only its covariance
    expected = np.diag(np.radians([0.5, 0.5, 0.5, 2.0, 2.0]) ** 2)
    np.testing.assert_allclose(floored.cov_55 - raw.cov_55, expected, rtol=1e-9, atol=1e-15)
    assert floored.sigma_rot_rad >= math.radians(0.5) and floored.sigma_dir_rad >= math.radians(2.0)


def _correlated_estimate() -> KeypointPose:
    """By hand: R = I, direction +z, basis (x, y); the rotation about y and the direction's x component have
    variance 1e-4 each and covariance 5e-5 (correlation 0.5), everything else 1e-4 and uncorrelated."""
    S = np.diag([1e-4] * 5)
    S[1, 3] = S[3, 1] = 5e-5
    return KeypointPose(True, None, np.eye(3), np.array([0.0, 0.0, 1.0]), 100, 100, 10.0, 0.01, 0.01, S,
                        np.array([[1.0, 0.0], [0.0, 1.0], [0.0, 0.0]]))


def test_the_rotation_given_a_direction_is_the_linear_conditional():
    kp = _correlated_estimate()
    u = np.array([0.01, 0.0, 1.0])                      # the direction from elsewhere: 0.01 rad towards +x
    R, cov = kp.rotation_given_direction(u)
    # e = B^T (t - u/|u|) = (-0.01/|u|, 0); shift = -G e with G = S_rd S_dd^-1 = 0.5 on (y, x): +0.005 rad about y
    shift = cv2.Rodrigues(R)[0].ravel()
    np.testing.assert_allclose(shift, [0.0, 0.5 * 0.01 / math.sqrt(1.0001), 0.0], atol=1e-9)
    np.testing.assert_allclose(cov, np.diag([1e-4, 1e-4 - 5e-5 ** 2 / 1e-4, 1e-4]), atol=1e-15)
    # the same direction as the estimate's: the rotation is unchanged, its covariance still the conditional one
    R0, cov0 = kp.rotation_given_direction(np.array([0.0, 0.0, 2.0]))
    np.testing.assert_allclose(R0, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(cov0, cov, atol=1e-15)
    # a direction 40 deg away is not a small offset: the rotation's marginal
    R40, cov40 = kp.rotation_given_direction(np.array([math.sin(math.radians(40)), 0.0, math.cos(math.radians(40))]))
    np.testing.assert_allclose(R40, np.eye(3))
    np.testing.assert_allclose(cov40, np.diag([1e-4] * 3))


def test_a_rotation_only_factor_covariance_frees_the_translation():
    kp = _correlated_estimate()
    kp.R_b_a = cv2.Rodrigues(np.array([[0.0], [0.0], [math.pi / 2]]))[0]
    C = np.diag([1e-4, 2e-4, 3e-4])
    cov = kp.rotation_covariance_gtsam(C, 100.0)
    np.testing.assert_allclose(cov[3:, 3:], np.eye(3) * 100.0, atol=1e-12)
    np.testing.assert_allclose(cov[:3, 3:], 0.0, atol=1e-15)
    # in frame a's axes: b's x is a's y after the 90 deg turn about z (R_b_a^T C R_b_a)
    np.testing.assert_allclose(np.diag(cov[:3, :3]), [2e-4, 1e-4, 3e-4], atol=1e-15)


def test_the_true_direction_sharpens_the_rotation_on_a_rendered_pair():
    # frames 0 and 4 of rendered room 7 with the refiner's keypoint settings: the rotation given the true direction
    # errs several times less than the rotation estimated with the keypoints' own direction (0.06 vs 0.39 deg)
    from dpv_sensor.data.synthetic import render_sequence
    seq = render_sequence(seed=7, num_frames=5, width=320, height=240, plain_wall_prob=0.0)
    T_b_a = np.linalg.inv(seq.pose(4)) @ seq.pose(0)
    kp = keypoint_relative_pose(seq.image(0), seq.image(4), np.asarray(seq.K, np.float64), KeypointConfig())
    assert kp.ok and kp.t_dir_b is not None, kp.reason
    R_cond, cov_cond = kp.rotation_given_direction(T_b_a[:3, 3])
    marginal, conditional = _rot_err_deg(kp.R_b_a, T_b_a), _rot_err_deg(R_cond, T_b_a)
    assert conditional < 0.5 * marginal, (marginal, conditional)
    assert np.trace(cov_cond) < np.trace(kp.rotation_covariance())


def _opencv_ratio_matches(desc_a, desc_b, ratio):
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(desc_a, desc_b, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < ratio * p[1].distance]
    return [(m.queryIdx, m.trainIdx) for m in good]


def test_l2_matching_is_opencvs_brute_force_match_for_match(pair):
    """The matrix-product matcher returns exactly the pairs OpenCV's brute-force knnMatch + ratio test does, on
    the SIFT descriptors of rendered views (both directions, two ratios)."""
    from dpv_sensor.core.keypoint_pose import _match_l2, detect_features
    fa, fb = (detect_features(im) for im in pair[:2])
    assert len(fa.keypoints) > 100 and len(fb.keypoints) > 100
    for da, db in ((fa.descriptors, fb.descriptors), (fb.descriptors, fa.descriptors)):
        for ratio in (0.8, 0.6):
            ia, ib = _match_l2(da, db, ratio)
            want = _opencv_ratio_matches(da, db, ratio)
            assert len(want) > 20
            assert list(zip(ia.tolist(), ib.tolist())) == want


def test_l2_matching_ratio_test_by_hand():
    """Distances by hand: a0 is 3 from b0 and sqrt(73) from b1 (b2 is far), so it passes a ratio just above
    3 / sqrt(73) and fails at exactly that ratio; a1 is 4 from both b0 and b1 and never passes."""
    from dpv_sensor.core.keypoint_pose import _match_l2
    b = np.zeros((3, 128), np.float32)
    b[1, 0] = 8.0
    b[2, :] = 100.0
    a = np.zeros((2, 128), np.float32)
    a[0, 1] = 3.0
    a[1, 0] = 4.0
    ia, ib = _match_l2(a, b, 0.8)
    assert ia.tolist() == [0] and ib.tolist() == [0]
    ia, ib = _match_l2(a, b, 3.0 / math.sqrt(73.0))       # exactly the ratio: not below it
    assert ia.tolist() == []
    ia, ib = _match_l2(a, b, 3.0 / math.sqrt(73.0) + 1e-6)
    assert ia.tolist() == [0] and ib.tolist() == [0]
    assert _match_l2(a, b[:1], 0.8)[0].tolist() == []     # one descriptor: no second neighbour


def test_the_sampson_jacobian_is_the_central_difference_of_the_distance():
    """float64: the analytic Jacobian of the Sampson distance with respect to a left rotation increment and a move
    of the direction in its tangent plane, against central differences of the distance itself."""
    from dpv_sensor.core.keypoint_pose import _apply, _basis, sampson_jacobian, sampson_px
    rng = np.random.default_rng(0)
    n = 40
    xa = np.c_[rng.normal(size=(n, 2)) * 0.5, np.ones(n)]
    xb = np.c_[rng.normal(size=(n, 2)) * 0.5, np.ones(n)]
    R = cv2.Rodrigues(np.array([[0.1], [-0.2], [0.05]]))[0]
    t = np.array([0.3, -0.1, 0.9])
    t /= np.linalg.norm(t)
    B = _basis(t)
    r, J = sampson_jacobian(xa, xb, R, t, 500.0, B)
    assert np.allclose(r, sampson_px(xa, xb, R, t, 500.0), rtol=1e-12, atol=1e-9)
    J_fd = np.empty((n, 5))
    for k in range(5):
        d = np.zeros(5)
        d[k] = 1e-6
        plus, minus = _apply(R, t, B, d), _apply(R, t, B, -d)
        J_fd[:, k] = (sampson_px(xa, xb, *plus, 500.0) - sampson_px(xa, xb, *minus, 500.0)) / 2e-6
    assert np.abs(J - J_fd).max() < 1e-5 * np.abs(J_fd).max()
    assert np.allclose(sampson_jacobian(xa, xb, R, t, 500.0)[1], J[:, :3])      # rotation only
