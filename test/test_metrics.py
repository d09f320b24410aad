"""Depth metrics on hand-computed cases (dpv_sensor/metrics.py)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from dpv_sensor import metrics as M


def _gt(h=6, w=10, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform(0.5, 5.0, size=(h, w))


def test_perfect_prediction():
    gt = _gt()
    r = M.depth_metrics(gt.copy(), gt)
    assert r['abs_rel'] == 0 and r['sq_rel'] == 0 and r['rmse'] == 0 and r['rmse_log'] == 0
    assert r['delta1'] == 1 and r['delta2'] == 1 and r['delta3'] == 1
    assert r['si_log'] == pytest.approx(0, abs=1e-7)
    assert r['coverage'] == 1 and r['num_pixels'] == gt.size


def test_constant_scale_error_1p1():
    gt = np.array([[1.0, 2.0], [3.0, 4.0]])
    pred = 1.1 * gt
    r = M.depth_metrics(pred, gt)
    assert r['abs_rel'] == pytest.approx(0.1)
    # sq_rel = mean((0.1 g)^2 / g) = 0.01 * mean(g) = 0.01 * 2.5
    assert r['sq_rel'] == pytest.approx(0.025)
    # rmse = 0.1 * sqrt(mean(g^2)) = 0.1 * sqrt(30 / 4)
    assert r['rmse'] == pytest.approx(0.1 * math.sqrt(7.5))
    assert r['rmse_log'] == pytest.approx(math.log(1.1))
    assert r['si_log'] == pytest.approx(0, abs=1e-7)          # a pure scale error is scale-invariant
    assert r['delta1'] == 1 and r['delta2'] == 1 and r['delta3'] == 1   # 1.1 < 1.25
    ms = M.depth_metrics(pred, gt, median_scaling=True)
    assert ms['abs_rel'] == pytest.approx(0, abs=1e-12)
    assert ms['rmse'] == pytest.approx(0, abs=1e-12)
    assert ms['scale'] == pytest.approx(1 / 1.1)


def test_constant_scale_error_1p3():
    gt = _gt()
    r = M.depth_metrics(1.3 * gt, gt)
    assert r['delta1'] == 0            # 1.3 > 1.25
    assert r['delta2'] == 1            # 1.3 < 1.5625
    assert r['abs_rel'] == pytest.approx(0.3)
    # underestimation by the same ratio gives the same deltas
    r2 = M.depth_metrics(gt / 1.3, gt)
    assert r2['delta1'] == 0 and r2['delta2'] == 1


def test_known_outlier_fraction():
    gt = _gt(10, 10)
    pred = gt.copy()
    pred.reshape(-1)[::10] *= 3.0        # exactly 10 of 100 pixels
    r = M.depth_metrics(pred, gt)
    assert r['delta1'] == pytest.approx(0.9)
    assert r['delta2'] == pytest.approx(0.9)          # 3 > 1.5625
    assert r['delta3'] == pytest.approx(0.9)          # 3 > 1.953
    assert r['abs_rel'] == pytest.approx(0.1 * 2.0)   # 10 % of pixels with |3g - g| / g = 2
    # median scaling uses median(gt) / median(pred) (not the median ratio): on a constant GT the
    # outliers do not move the medians, so the scale stays 1
    flat = np.full((10, 10), 2.0)
    pflat = flat.copy()
    pflat.reshape(-1)[::10] *= 3.0
    ms = M.depth_metrics(pflat, flat, median_scaling=True)
    assert ms['scale'] == pytest.approx(1.0)
    assert ms['delta1'] == pytest.approx(0.9)


def test_invalid_pixels_are_ignored():
    gt = _gt(4, 5)
    pred = gt.copy()
    gt[0, 0] = 0.0              # no GT: a wildly wrong prediction there must not count
    pred[0, 0] = 100.0
    gt[0, 1] = np.nan
    pred[0, 1] = 100.0
    gt[0, 2] = np.inf
    pred[1, 0] = np.nan         # no prediction: not scored, lowers coverage
    pred[1, 1] = 0.0            # 0 = no prediction (16UC1 convention)
    pred[1, 2] = -1.0
    r = M.depth_metrics(pred, gt)
    assert r['abs_rel'] == 0 and r['delta1'] == 1
    n_gt = 20 - 3
    assert r['num_pixels'] == n_gt - 3
    assert r['coverage'] == pytest.approx((n_gt - 3) / n_gt)


def test_depth_limits_restrict_gt_and_clip_pred():
    gt = np.array([[1.0, 2.0, 20.0]])
    pred = np.array([[1.0, 30.0, 20.0]])
    r = M.depth_metrics(pred, gt, max_depth=10.0)
    # the 20 m GT pixel is out of range; the 30 m prediction is clipped to 10 m -> |10-2|/2 = 4
    assert r['num_pixels'] == 2
    assert r['abs_rel'] == pytest.approx((0 + 4.0) / 2)


def test_no_valid_pixel_gives_nan():
    r = M.depth_metrics(np.ones((3, 3)), np.zeros((3, 3)))
    assert math.isnan(r['abs_rel']) and r['num_pixels'] == 0 and math.isnan(r['coverage'])


def test_shape_mismatch_raises():
    with pytest.raises(ValueError, match='shape'):
        M.depth_metrics(np.ones((3, 3)), np.ones((3, 4)))


def test_si_log_matches_eigen_definition():
    rng = np.random.default_rng(3)
    gt = _gt(8, 8)
    pred = gt * np.exp(rng.normal(0, 0.2, gt.shape)) * 1.7
    d = np.log(pred) - np.log(gt)
    r = M.depth_metrics(pred, gt)
    assert r['si_log'] == pytest.approx(math.sqrt(np.mean(d ** 2) - np.mean(d) ** 2))
    # invariant to a global scale
    assert M.depth_metrics(pred * 5.0, gt)['si_log'] == pytest.approx(r['si_log'])


# ---------------------------------------------------------------------------------------------
# Confidence quality
# ---------------------------------------------------------------------------------------------

def test_sparsification_by_hand():
    err = np.array([1.0, 2.0, 3.0, 4.0])
    fr = np.array([0.0, 0.25, 0.5, 0.75])
    perfect = M.sparsification(err, -err, fr)
    np.testing.assert_allclose(perfect['sparsification'], [2.5, 2.0, 1.5, 1.0])
    np.testing.assert_allclose(perfect['oracle'], [2.5, 2.0, 1.5, 1.0])
    np.testing.assert_allclose(perfect['random'], [2.5] * 4)
    assert M.ause(perfect) == 0.0
    worst = M.sparsification(err, err, fr)     # most confident where the error is largest
    np.testing.assert_allclose(worst['sparsification'], [2.5, 3.0, 3.5, 4.0])
    # trapezoid of (0, 1, 2, 3) with step 0.25
    assert M.ause(worst) == pytest.approx(0.25 * (0.5 + 1.5 + 2.5))
    assert M.aurg(worst) < 0 < M.aurg(perfect)


def test_ause_zero_for_perfect_confidence_default_fractions():
    rng = np.random.default_rng(1)
    err = rng.exponential(0.1, size=2000)
    conf = 1.0 / (1.0 + err)                  # monotone in the error
    assert M.ause(M.sparsification(err, conf)) == pytest.approx(0.0, abs=1e-12)
    noisy = M.sparsification(err, rng.uniform(size=err.size))
    assert M.ause(noisy) > 0.01


def test_confident_half_ratio():
    err = np.array([1.0, 2.0, 3.0, 4.0])
    conf = np.array([0.9, 0.8, 0.2, 0.1])
    assert M.confident_half_ratio(err, conf) == pytest.approx(1.5 / 2.5)
    assert M.confident_half_ratio(err, conf[::-1]) == pytest.approx(3.5 / 2.5)


# ---------------------------------------------------------------------------------------------
# Accumulation
# ---------------------------------------------------------------------------------------------

def test_accumulator_frame_mean_vs_pixel_weighted():
    acc = M.MetricAccumulator()
    gt1 = np.array([[1.0, 2.0], [3.0, 4.0]])
    acc.add(1.1 * gt1, gt1, index=0)                 # 4 pixels, abs_rel 0.1
    gt2 = np.array([[2.0, 0.0], [0.0, 0.0]])
    acc.add(gt2.copy(), gt2, index=1)               # 1 pixel, abs_rel 0
    s = acc.summary()
    assert s['num_frames'] == 2 and s['headline'] == 'frame_mean'
    assert s['metric']['frame_mean']['abs_rel'] == pytest.approx(0.05)
    assert s['metric']['pixel_weighted']['abs_rel'] == pytest.approx(0.4 / 5)
    assert s['median_scaled']['frame_mean']['abs_rel'] == pytest.approx(0.0, abs=1e-12)
    assert s['coverage']['pixel_weighted'] == 1.0
    assert acc.rows[0]['index'] == 0 and acc.rows[0]['ms_abs_rel'] == pytest.approx(0, abs=1e-12)
    assert 'confidence' not in s


def test_accumulator_confidence_and_temporal():
    rng = np.random.default_rng(2)
    gt = _gt(10, 10)
    pred = gt * (1 + rng.normal(0, 0.1, gt.shape))
    err = np.abs(pred - gt) / gt
    acc = M.MetricAccumulator()
    row = acc.add(pred, gt, confidence=1.0 - err / err.max())
    assert row['ause'] == pytest.approx(0.0, abs=1e-12)
    assert row['confident_half_ratio'] < 1.0
    acc.add_temporal(0.02, 100)
    acc.add_temporal(0.04, 300)
    acc.add_temporal(float('nan'), 0)
    s = acc.summary()
    assert s['confidence']['ause_frame_mean'] == pytest.approx(0.0, abs=1e-12)
    assert s['temporal_consistency']['pair_mean'] == pytest.approx(0.03)
    assert s['temporal_consistency']['pixel_weighted'] == pytest.approx((2 + 12) / 400)
    assert s['temporal_consistency']['num_pairs'] == 2
    curves = acc.mean_curves()
    np.testing.assert_allclose(curves['sparsification'], curves['oracle'])


# ---------------------------------------------------------------------------------------------
# Temporal consistency
# ---------------------------------------------------------------------------------------------

def _plane_depth(K, T_world_cam, n, c, h, w):
    """Analytic z-depth of the world plane n.X = c seen by a camera (ray z-component 1)."""
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    rays = np.linalg.inv(K) @ np.stack([u.ravel(), v.ravel(), np.ones(h * w)])
    R, t = T_world_cam[:3, :3], T_world_cam[:3, 3]
    s = (c - n @ t) / (n @ (R @ rays))
    return s.reshape(h, w)


def _scene(T_b):
    h, w = 30, 40
    K = np.array([[40.0, 0, (w - 1) / 2], [0, 40.0, (h - 1) / 2], [0, 0, 1]])
    n = np.array([0.2, -0.1, 1.0])
    c = 3.0
    T_a = np.eye(4)
    return K, T_a, _plane_depth(K, T_a, n, c, h, w), _plane_depth(K, T_b, n, c, h, w)


def test_temporal_consistency_zero_for_exact_depth_of_translation():
    T_b = np.eye(4)
    T_b[:3, 3] = [0.15, -0.05, 0.3]
    K, T_a, da, db = _scene(T_b)
    val, n = M.temporal_consistency(da, db, K, K, T_a, T_b)
    assert n > 0.5 * da.size
    # bilinear sampling of a slanted plane's depth is not exactly linear: tiny residual only
    assert val < 1e-4
    # exact GT for both frames: visibility from GT keeps (almost) all those pixels
    val2, n2 = M.temporal_consistency(da, db, K, K, T_a, T_b, gt_a=da, gt_b=db)
    assert val2 < 1e-4 and n2 == n
    # a 10 % scale error in frame b shows up as a 10 % inconsistency
    val3, _ = M.temporal_consistency(da, 1.1 * db, K, K, T_a, T_b)
    assert val3 == pytest.approx(0.1, abs=1e-3)


def test_temporal_consistency_with_rotation_and_wrong_pose_convention():
    from scipy.spatial.transform import Rotation
    T_b = np.eye(4)
    T_b[:3, :3] = Rotation.from_rotvec([0.02, -0.05, 0.01]).as_matrix()
    T_b[:3, 3] = [0.1, 0.0, 0.1]
    K, T_a, da, db = _scene(T_b)
    val, n = M.temporal_consistency(da, db, K, K, T_a, T_b)
    assert n > 0 and val < 1e-4
    # swapping the poses (the inverted convention) is clearly inconsistent
    bad, _ = M.temporal_consistency(da, db, K, K, T_b, T_a)
    assert bad > 0.01


def test_temporal_consistency_occlusion_mask_from_gt():
    # frame a sees a far wall; in frame b an occluder covers the left part: its predicted depth is
    # correct for b, yet inconsistent with a's wall points. GT visibility excludes those pixels.
    h, w = 20, 30
    K = np.array([[30.0, 0, (w - 1) / 2], [0, 30.0, (h - 1) / 2], [0, 0, 1]])
    T = np.eye(4)
    da = np.full((h, w), 4.0)
    db = da.copy()
    db[:, :10] = 1.0
    val, n = M.temporal_consistency(da, db, K, K, T, T)
    assert val == pytest.approx(0.75 * 10 / 30, rel=1e-6) and n == h * w
    val_vis, n_vis = M.temporal_consistency(da, db, K, K, T, T, gt_a=da, gt_b=db)
    assert val_vis == pytest.approx(0.0, abs=1e-12)
    # columns 0..9 occluded, column 10's bilinear neighbours straddle the edge only at u < 10
    assert n_vis == h * (w - 10)


def test_temporal_consistency_none_visible():
    K = np.array([[10.0, 0, 4.5], [0, 10.0, 4.5], [0, 0, 1]])
    T_b = np.eye(4)
    T_b[:3, 3] = [100.0, 0, 0]
    d = np.full((10, 10), 2.0)
    val, n = M.temporal_consistency(d, d, K, K, np.eye(4), T_b)
    assert n == 0 and math.isnan(val)


def test_dpv_nll_uses_the_dpv_helper():
    import torch
    from dpv_sensor import dpv
    depths = dpv.depth_planes(0.5, 5.0, 8, dtype=torch.float64)
    idx = torch.tensor([[[2, 5], [0, 7]]])
    sharp = dpv.one_hot_log(idx, 8, floor=-30.0).double()
    gt = depths[idx]
    assert M.dpv_nll(sharp, depths, gt) == pytest.approx(0.0, abs=1e-9)
    uniform = dpv.uniform_log(1, 8, 2, 2, dtype=torch.float64)
    assert M.dpv_nll(uniform.numpy(), depths.numpy(), gt.numpy()) == pytest.approx(math.log(8))
    # a masked-out pixel with a wrong DPV does not count
    wrong = sharp.clone()
    wrong[0, :, 0, 0] = dpv.one_hot_log(torch.tensor([[[7]]]), 8).double()[0, :, 0, 0]
    assert M.dpv_nll(wrong, depths, gt) > 5.0
    mask = torch.ones(1, 2, 2, dtype=torch.bool)
    mask[0, 0, 0] = False
    assert M.dpv_nll(wrong, depths, gt, mask) == pytest.approx(0.0, abs=1e-9)


def test_confident_half_pooled_ranks_frames_against_each_other():
    """Two frames, each uniformly right or wrong and uniformly confident: within a frame the confidence cannot
    rank anything (per-frame ratio 1), pooled it picks the good frame (0.1 / mean(0.1, 0.5) = 1/3)."""
    acc = M.MetricAccumulator(min_depth=0.1, max_depth=10.0)
    gt = np.full((16, 16), 2.0)
    acc.add(np.full_like(gt, 2.2), gt, np.full_like(gt, 0.9))    # abs_rel 0.1, confident
    acc.add(np.full_like(gt, 3.0), gt, np.full_like(gt, 0.1))    # abs_rel 0.5, not
    c = acc.summary()['confidence']
    assert c['confident_half_ratio_frame_mean'] == pytest.approx(1.0)
    assert c['confident_half_ratio_pooled'] == pytest.approx(0.1 / 0.3)
    assert len(acc._pooled[0][0]) == 16 * 16 // acc.pool_stride
    assert np.isnan(M.MetricAccumulator().pooled_confident_half_ratio())


def test_constant_baseline_is_the_median_gt_on_the_scored_pixels():
    from dpv_sensor.metrics import MetricAccumulator
    gt = np.array([[1.0, 2.0, 2.2, 4.0, 0.0]])
    pred = np.array([[1.0, 2.0, 2.0, np.nan, 3.0]])          # scored: the first three pixels (GT 1, 2, 2.2)
    acc = MetricAccumulator()
    row = acc.add(pred, gt)
    # constant = median(1, 2, 2.2) = 2: relative errors 1, 0, 0.2 / 2.2; 2 / 1 > 1.25 fails delta1
    assert row['const_abs_rel'] == pytest.approx((1.0 + 0.2 / 2.2) / 3)
    assert row['const_delta1'] == pytest.approx(2 / 3)
    assert acc.summary()['constant']['frame_mean']['abs_rel'] == pytest.approx((1.0 + 0.2 / 2.2) / 3)
