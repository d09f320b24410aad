"""Pose uncertainty in the measurement: hand-computed cases on a tiny pinhole camera and a fronto-parallel plane."""
import math

import numpy as np
import pytest
import torch

from dpv_sensor.core import dpv as dpv_ops
from dpv_sensor.core import parallax
from dpv_sensor.core import pose_uncertainty as PU


def _K(f=100.0, cx=15.5, cy=11.5):
    return torch.tensor([[[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]]])


def _T(t=(0.0, 0.0, 0.0), rotvec=(0.0, 0.0, 0.0)):
    from scipy.spatial.transform import Rotation
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def test_drift_on_a_straight_metre_and_a_turn():
    m = PU.DriftModel(trans_per_m=0.02, rot_deg_per_m=1.0, rot_per_deg=0.02, sync_s=0.0)
    s = PU.relative_pose_sigma(m, [_T(), _T((0.5, 0, 0)), _T((1.0, 0, 0))])
    assert s.trans_m == pytest.approx(0.02 / math.sqrt(3))
    assert s.rot_rad == pytest.approx(math.radians(1.0) / math.sqrt(3))
    # turning 10 deg in place: 2 % of 10 deg, no translation error
    s = PU.relative_pose_sigma(m, [_T(), _T(rotvec=(0, math.radians(10), 0))])
    assert s.trans_m == pytest.approx(0.0)
    assert s.rot_rad == pytest.approx(math.radians(0.2) / math.sqrt(3))


def test_time_offset_cancels_for_constant_velocity_and_counts_the_velocity_change():
    m = PU.DriftModel(trans_per_m=0.0, rot_deg_per_m=0.0, rot_per_deg=0.0, sync_s=0.01)
    v = np.array([0.3, 0, 0, 0, 0.5, 0])
    s = PU.relative_pose_sigma(m, [_T(), _T((0.1, 0, 0))], twist_ref_6=v, twist_src_6=v)
    assert s.trans_m == pytest.approx(0.0) and s.rot_rad == pytest.approx(0.0)
    s = PU.relative_pose_sigma(m, [_T(), _T((0.1, 0, 0))], twist_ref_6=v, twist_src_6=np.array([0.3, 0, 0, 0, -0.5, 0]))
    assert s.rot_rad == pytest.approx(0.01 * 1.0 / math.sqrt(3))
    assert s.trans_m == pytest.approx(0.0)


def test_twist_between_two_poses():
    tw = PU.twist_between(_T(), _T((0.02, 0, 0), (0, 0, 0.01)), 0.1)
    np.testing.assert_allclose(tw, [0.2, 0, 0, 0, 0, 0.1], atol=1e-9)
    assert PU.twist_between(_T(), _T(), 0.0) is None


def test_covariance_growth_replaces_the_drift_terms_and_unfilled_covariance_is_ignored():
    m = PU.DriftModel(sync_s=0.0, cov_trans_per_m=0.05)     # a cap that does not bind: (0.05 * 1 m)^2 / 3 > 4e-4
    a = np.diag([1e-4] * 3 + [1e-6] * 3)
    b = np.diag([5e-4] * 3 + [5e-6] * 3)
    s = PU.relative_pose_sigma(m, [_T(), _T((1.0, 0, 0))], odom_first=a, odom_last=b)
    assert s.trans_m == pytest.approx(0.02)          # sqrt(4e-4)
    assert s.rot_rad == pytest.approx(0.002)         # sqrt(4e-6)
    assert PU.covariance_sigma(a, np.zeros((6, 6))) is None
    assert PU.covariance_sigma(a, None) is None


def test_covariance_translation_growth_is_capped_by_the_relative_motion():
    # growth 4e-4 m^2 (2 cm) over a 1 m path: the cap is (0.02 * 1)^2 / 3 + 4e-6 * 1^2 / 3 = 1.34667e-4 m^2
    m = PU.DriftModel(sync_s=0.0)                            # cov_trans_per_m 0.02
    a = np.diag([1e-4] * 3 + [1e-6] * 3)
    b = np.diag([5e-4] * 3 + [5e-6] * 3)
    s = PU.relative_pose_sigma(m, [_T(), _T((0.5, 0, 0)), _T((1.0, 0, 0))], odom_first=a, odom_last=b)
    assert s.trans_m == pytest.approx(math.sqrt(0.02 ** 2 / 3 + 4e-6 / 3))
    assert s.rot_rad == pytest.approx(0.002)                 # the rotation growth is taken as it is
    # a growth below the cap is kept; with no path (turning in place) only the rotation's lever is left: 0
    small = np.diag([2e-4] * 3 + [5e-6] * 3)                  # growth 1e-4 m^2: 1 cm, under the cap
    assert PU.relative_pose_sigma(m, [_T(), _T((1.0, 0, 0))], odom_first=a,
                                  odom_last=small).trans_m == pytest.approx(0.01)
    assert PU.relative_pose_sigma(m, [_T(), _T(rotvec=(0, 0.1, 0))], odom_first=a, odom_last=b).trans_m == 0.0


def test_match_shift_at_the_principal_point_and_off_axis():
    d = torch.full((1, 24, 32), 2.0)
    sig = PU.PoseSigma(rot_rad=0.001, trans_m=0.004)
    shift = PU.match_shift_px(d, _K(cx=15.0, cy=11.0), sig)
    assert float(shift[0, 11, 15]) == pytest.approx(100.0 * math.sqrt(0.001 ** 2 + 0.002 ** 2), rel=1e-5)
    # 10 px right of the principal point: lever sqrt(f^2 + r^2 / 2)
    assert float(shift[0, 11, 25]) == pytest.approx(math.sqrt(100.0 ** 2 + 50.0) * math.sqrt(5e-6), rel=1e-5)


def test_inverse_depth_sigma_on_a_plane_matches_the_hand_computation():
    """Camera translating sideways by b in front of a plane at depth d: the band [d/k, d k] spans f b (k - 1/k) / d
    pixels, so a match shift of e pixels is e / (f b) in inverse depth."""
    f, b, d, k = 100.0, 0.1, 2.0, parallax.BAND_RATIO
    depth = torch.full((1, 24, 32), d)
    T_src_ref = torch.tensor(_T((-b, 0, 0)), dtype=torch.float32)[None, None]
    span = parallax.disparity_span(depth, _K(), T_src_ref, k, per_source=True)          # 1, 1, H, W
    assert float(span[0, 0, 11, 15]) == pytest.approx(f * b * (k - 1 / k) / d, rel=1e-3)
    e = torch.full_like(span, 0.5)
    sig = PU.inverse_depth_sigma(depth, span, e, k)
    assert float(sig[0, 11, 15]) == pytest.approx(0.5 / (f * b), rel=1e-3)
    # two such sources: half the variance; a source that does not see the pixel adds nothing
    sig2 = PU.inverse_depth_sigma(depth, torch.cat([span, span]), torch.cat([e, e]), k)
    assert float(sig2[0, 11, 15]) == pytest.approx(0.5 / (f * b) / math.sqrt(2), rel=1e-3)
    sig0 = PU.inverse_depth_sigma(depth, torch.cat([span, torch.zeros_like(span)]), torch.cat([e, e]), k)
    assert float(sig0[0, 11, 15]) == pytest.approx(float(sig[0, 11, 15]))
    assert math.isinf(float(PU.inverse_depth_sigma(depth, torch.zeros_like(span), e, k)[0, 0, 0]))


def test_widening_a_peaked_measurement_gives_the_gaussian():
    D = 41
    logp = torch.full((1, D, 1, 2), -1e4)
    logp[:, 20] = 0.0
    logp = torch.log_softmax(logp, 1)
    sig = torch.tensor([[[0.0, 2.0]]])
    out = PU.widen_planes(logp, sig)
    torch.testing.assert_close(out[..., 0], logp[..., 0])
    p = out[0, :, 0, 1].exp()
    i = torch.arange(D, dtype=torch.float32)
    g = torch.exp(-0.5 * ((i - 20) / 2.0) ** 2)
    torch.testing.assert_close(p, g / g.sum(), atol=1e-6, rtol=1e-4)
    # a width between two ladder steps mixes them: 3 planes = half of 2 and half of 4
    mid = PU.widen_planes(logp, torch.tensor([[[3.0, 3.0]]]))[0, :, 0, 0].exp()
    g4 = torch.exp(-0.5 * ((i - 20) / 4.0) ** 2)
    torch.testing.assert_close(mid, 0.5 * g / g.sum() + 0.5 * g4 / g4.sum(), atol=1e-6, rtol=1e-4)


def test_a_larger_pose_covariance_never_raises_the_confidence():
    """The full chain on a plane: covariance -> pixel shift -> inverse-depth std -> widened DPV -> ratio confidence."""
    D, H, W = 32, 6, 8
    depths = dpv_ops.depth_planes(0.5, 8.0, D, torch.float32, 'cpu')
    torch.manual_seed(0)
    logp = torch.log_softmax(torch.randn(1, D, H, W) * 3.0, 1)
    depth = torch.full((1, H, W), 2.0)
    K = _K(f=20.0, cx=3.5, cy=2.5)
    T_src_ref = torch.tensor(_T((-0.1, 0, 0)), dtype=torch.float32)[None, None]
    span = parallax.disparity_span(depth, K, T_src_ref, parallax.BAND_RATIO, per_source=True)
    step = (1 / 0.5 - 1 / 8.0) / (D - 1)
    prev = None
    for var in (0.0, 1e-6, 1e-5, 1e-4, 1e-3):
        sigma = PU.covariance_sigma(np.eye(6) * 1e-8, np.eye(6) * (1e-8 + var)) if var else PU.PoseSigma(0.0, 0.0)
        shift = PU.match_shift_px(depth, K, sigma)[None]
        planes = PU.inverse_depth_sigma(depth, span, shift, parallax.BAND_RATIO) / step
        out = PU.widen_planes(logp, planes)
        d_out = dpv_ops.depth_estimate(out, depths, 'relative')
        conf = dpv_ops.ratio_confidence(out, depths, d_out, 1.25)
        mass = float(out.exp().amax(1).mean())
        if prev is not None:
            assert mass <= prev[0] + 1e-6
            assert float(conf.mean()) <= prev[1] + 1e-4
        prev = (mass, float(conf.mean()))
    assert prev[1] < 0.5
