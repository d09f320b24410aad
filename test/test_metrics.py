"""Depth metrics on hand-computed cases (dpv_sensor/evaluation/metrics.py)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from dpv_sensor.evaluation import metrics as M


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
    from dpv_sensor.core import dpv
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
    from dpv_sensor.evaluation.metrics import MetricAccumulator
    gt = np.array([[1.0, 2.0, 2.2, 4.0, 0.0]])
    pred = np.array([[1.0, 2.0, 2.0, np.nan, 3.0]])          # scored: the first three pixels (GT 1, 2, 2.2)
    acc = MetricAccumulator()
    row = acc.add(pred, gt)
    # constant = median(1, 2, 2.2) = 2: relative errors 1, 0, 0.2 / 2.2; 2 / 1 > 1.25 fails delta1
    assert row['const_abs_rel'] == pytest.approx((1.0 + 0.2 / 2.2) / 3)
    assert row['const_delta1'] == pytest.approx(2 / 3)
    assert acc.summary()['constant']['frame_mean']['abs_rel'] == pytest.approx((1.0 + 0.2 / 2.2) / 3)


# ----------------------------------------------------------------------------------------------
# depth edges and planar normals
# ----------------------------------------------------------------------------------------------

def _step_gt(h=20, w=40, near=1.0, far=2.0, col=20):
    gt = np.full((h, w), near)
    gt[:, col:] = far
    return gt


def test_edge_band_is_the_columns_within_radius_of_the_jump():
    gt = _step_gt()
    band = M.depth_edge_band(gt, jump=0.10, radius=3)
    # the jump lies between columns 19 and 20: both are edge pixels, the band is columns 16..23
    expected = np.zeros_like(band)
    expected[:, 16:24] = True
    assert np.array_equal(band, expected)
    # a 5 % step is not a jump at 10 %, and invalid GT makes no edge
    assert not M.depth_edge_band(_step_gt(far=1.05)).any()
    holes = np.full((20, 40), 1.0)
    holes[:, 20:] = 0.0
    assert not M.depth_edge_band(holes).any()


def test_edge_abs_rel_separates_the_band_from_the_rest():
    gt = _step_gt()
    pred = gt.copy()
    pred[:, 16:24] *= 1.1             # 10 % wrong in the band only
    m = M.edge_planarity_metrics(pred, gt)
    assert m['edge_abs_rel'] == pytest.approx(0.1)
    assert m['nonedge_abs_rel'] == pytest.approx(0.0, abs=1e-12)
    assert m['edge_pixels'] == 20 * 8
    assert 'normal_err_deg' not in m  # no intrinsics, no normals


def _tilted_plane_depth(h, w, K, n, d):
    """z-depth of the plane n . X = d seen through K."""
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    return d / (rays @ np.asarray(n, np.float64))


def test_normals_of_a_tilted_plane_and_the_error_of_a_flat_prediction():
    h, w = 48, 64
    K = np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]])
    tilt = np.radians(30.0)
    n = np.array([0.0, np.sin(tilt), np.cos(tilt)])      # plane turned 30 degrees about the x axis
    gt = _tilted_plane_depth(h, w, K, n, 2.0)
    normals, ok = M.depth_normals(gt, K, window=7)
    assert ok[3:-3, 3:-3].all() and not ok[:3].any()     # a full 7x7 window is needed
    # facing the camera: the normal is -n
    assert np.allclose(normals[ok], -n, atol=1e-6)
    planar = M.planar_mask(gt, K)
    # planar needs a full window of GT normals: 3 more pixels off each border
    assert planar[6:-6, 6:-6].all() and planar.sum() == (h - 12) * (w - 12)
    m = M.edge_planarity_metrics(gt, gt, K)
    assert m['normal_err_deg'] == pytest.approx(0.0, abs=1e-3)
    assert m['planar_pixels'] == int(planar.sum())
    # a fronto-parallel prediction (constant depth) is 30 degrees off everywhere
    flat = np.full_like(gt, float(np.median(gt)))
    assert M.edge_planarity_metrics(flat, gt, K)['normal_err_deg'] == pytest.approx(30.0, abs=1e-3)


def test_terraces_raise_the_normal_error_but_not_on_a_smooth_plane():
    h, w = 48, 64
    K = np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]])
    n = np.array([0.0, np.sin(np.radians(60.0)), np.cos(np.radians(60.0))])
    gt = _tilted_plane_depth(h, w, K, n, 1.5)
    inv = 1.0 / gt
    step = (inv.max() - inv.min()) / 8                    # 8 terraces in inverse depth
    terraced = 1.0 / (np.round(inv / step) * step)
    m = M.edge_planarity_metrics(terraced, gt, K)
    assert m['normal_err_deg'] > 5.0
    assert M.edge_planarity_metrics(gt, gt, K)['normal_err_deg'] < 1e-3


def test_normal_window_grows_with_the_image():
    assert M.normal_window(64) == 7 and M.normal_window(320) == 21 and M.normal_window(640) == 41


def test_accumulator_reports_edges_and_normals():
    K = np.array([[30.0, 0, 20], [0, 30.0, 10], [0, 0, 1]])
    gt = _step_gt()
    pred = gt.copy()
    pred[:, 20:] *= 1.2               # the far half 20 % too far: half of the band and half of the rest
    acc = M.MetricAccumulator()
    row = acc.add(pred, gt, K=K)
    assert row['edge_abs_rel'] == pytest.approx(0.1)
    assert row['normal_err_deg'] == pytest.approx(0.0, abs=1e-3)   # both halves stay fronto-parallel
    e = acc.summary()['edges']
    assert e['edge_abs_rel_frame_mean'] == pytest.approx(0.1)
    assert e['nonedge_abs_rel_frame_mean'] == pytest.approx(0.1)


def test_ece_and_reliability_bins_by_hand():
    # bin [0.2, 0.3): 4 pixels at 0.25, 1 hit; bin [0.9, 1]: 4 pixels at 0.95, 4 hits
    conf = np.array([0.25] * 4 + [0.95] * 4)
    hit = np.array([1, 0, 0, 0, 1, 1, 1, 1], bool)
    r = M.reliability_bins(conf, hit)
    assert r['count'][2] == 4 and r['count'][9] == 4 and r['count'].sum() == 8
    assert r['hit_rate'][2] == pytest.approx(0.25) and r['mean_confidence'][9] == pytest.approx(0.95)
    assert np.isnan(r['hit_rate'][0])
    # |0.25 - 0.25| * 0.5 + |0.95 - 1| * 0.5
    assert M.expected_calibration_error(conf, hit) == pytest.approx(0.025)
    # confidence 1.0 falls in the last bin
    assert M.reliability_bins(np.array([1.0]), np.array([True]))['count'][9] == 1
    assert np.isnan(M.expected_calibration_error(np.zeros(0), np.zeros(0, bool)))


def test_ece_weights_each_bin_by_its_share_of_the_pixels():
    """Unequal bins: 1 pixel at 0.25 (a miss, |0.25 - 0| = 0.25) and 3 pixels at 0.95 (all hits, |0.95 - 1| =
    0.05): ECE = 1/4 * 0.25 + 3/4 * 0.05 = 0.1 (an unweighted mean over the bins would give 0.15)."""
    conf = np.array([0.25, 0.95, 0.95, 0.95])
    hit = np.array([0, 1, 1, 1], bool)
    assert M.expected_calibration_error(conf, hit) == pytest.approx(0.1)
    # and with the bins' sizes swapped: 3/4 * 0.25 + 1/4 * 0.05 = 0.2
    conf2 = np.array([0.25, 0.25, 0.25, 0.95])
    hit2 = np.array([0, 0, 0, 1], bool)
    assert M.expected_calibration_error(conf2, hit2) == pytest.approx(0.2)


def test_kept_at_thresholds_and_the_delta1_event():
    pred = np.array([1.0, 1.0, 1.0, 1.0])
    gt = np.array([1.0, 1.3, 0.79, 1.2])
    hit = M.within_ratio(pred, gt)
    np.testing.assert_array_equal(hit, [True, False, False, True])
    kept = M.kept_at_thresholds(np.array([0.95, 0.92, 0.6, 0.3]), hit)
    assert kept['0.9'] == {'share': 0.5, 'delta1': 0.5}
    assert kept['0.5']['share'] == pytest.approx(0.75) and kept['0.5']['delta1'] == pytest.approx(1 / 3)
    assert np.isnan(M.kept_at_thresholds(np.array([0.1]), np.array([True]))['0.9']['delta1'])


def test_accumulator_calibration_of_an_honest_and_an_overconfident_confidence():
    rng = np.random.default_rng(0)
    gt = np.full((64, 64), 2.0)
    # half of the pixels right (x1.1), half wrong (x1.5)
    wrong = rng.random(gt.shape) < 0.5
    pred = np.where(wrong, 3.0, 2.2)
    honest, over = M.MetricAccumulator(pool_stride=1), M.MetricAccumulator(pool_stride=1)
    honest.add(pred, gt, confidence=np.full(gt.shape, 0.5))
    over.add(pred, gt, confidence=np.full(gt.shape, 0.95))
    h, o = honest.summary()['calibration'], over.summary()['calibration']
    assert h['hit_rate'] == pytest.approx(1.0 - wrong.mean())
    assert h['ece'] == pytest.approx(abs(0.5 - h['hit_rate']))
    assert o['ece'] == pytest.approx(0.95 - o['hit_rate'])
    assert o['kept']['0.9']['share'] == 1.0 and h['kept']['0.9']['share'] == 0.0
