"""The odometry's covariances (core.odometry_covariance, core.pose_uncertainty.odometry_sigma, the window's factors):
each validation rule just either side of its threshold, the twist covariance integrated over a diff-drive step by
hand, the order of the sources (pose growth, twist, drift), and a huge covariance making a loose factor."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dpv_sensor.core import odometry_covariance as OC
from dpv_sensor.core import pose_uncertainty as PU
from dpv_sensor.stream.window_graph import (DRIFT, PUBLISHED, STEP_FLOOR_ROT_DEG, STEP_FLOOR_TRANS_M, TWIST,
                                            odometry_step_covariance, odometry_steps)
from dpv_sensor.stream.window_refiner import PoseRefinerConfig

# per-axis stds of a 6-dof odometry with different units and sizes on every axis (m, m, m, rad, rad, rad)
STD = np.array([0.02, 0.01, 0.05, 0.002, 0.004, 0.03])


def _correlated(rho: float, i: int = 0, j: int = 5) -> np.ndarray:
    """A covariance with STD on the diagonal and correlation `rho` between axes i and j (x and yaw by default)."""
    R = np.eye(6)
    R[i, j] = R[j, i] = rho
    return R * np.outer(STD, STD)


def _T(t=(0.0, 0.0, 0.0), rotvec=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


# ------------------------------------------------------------------------------------------------------------------
# validation, each rule just either side of its threshold
# ------------------------------------------------------------------------------------------------------------------
def test_a_valid_covariance_passes_symmetrised():
    C = _correlated(0.6)
    res = OC.check_covariance(C.reshape(-1))
    assert res.problem is None
    np.testing.assert_array_equal(res.matrix_66, C)


@pytest.mark.parametrize('factor,ok', [(0.9, True), (1.1, False)])
def test_asymmetry_just_under_and_over_the_tolerance(factor, ok):
    # the tolerance is in units of sqrt(C_ii C_jj) (x: 0.02 m, yaw: 0.03 rad): an absolute or a largest-variance
    # tolerance would take both (their difference is 6e-9 m rad)
    C = _correlated(0.3)
    C[5, 0] += factor * OC.SYMMETRY_TOL * STD[0] * STD[5]
    res = OC.check_covariance(C)
    if ok:
        assert res.problem is None
        assert res.matrix_66[0, 5] == res.matrix_66[5, 0] == pytest.approx(0.5 * (C[0, 5] + C[5, 0]))
    else:
        assert res.problem == OC.ASYMMETRIC and res.matrix_66 is None
        assert '[5][0] (rotation about z / x)' in res.detail and '[0][5]' in res.detail


@pytest.mark.parametrize('factor,ok', [(0.9, True), (1.1, False)])
def test_an_eigenvalue_just_above_and_below_minus_the_tolerance(factor, ok):
    # correlation -(1 + f tol) between y and rotation about x: the correlation-scaled matrix has eigenvalue -f tol,
    # the matrix itself one of about -f tol * 1e-2 * 2e-3 (an unscaled test would take both)
    C = _correlated(-(1.0 + factor * OC.PSD_TOL), 1, 3)
    assert np.linalg.eigvalsh(C)[0] > -OC.PSD_TOL * 1e-3
    res = OC.check_covariance(C)
    if ok:
        assert res.problem is None and res.matrix_66 is not None
    else:
        assert res.problem == OC.NOT_PSD and res.matrix_66 is None
        assert f'{-factor * OC.PSD_TOL:.3g}' in res.detail


def test_a_zero_variance_is_allowed_and_a_negative_one_is_a_fault():
    C = _correlated(0.2)
    C[2, 2] = 0.0                       # z of a planar robot: exact (its row is zero)
    res = OC.check_covariance(C)
    assert res.problem is None and res.matrix_66[2, 2] == 0.0
    C[2, 2] = -1e-12
    res = OC.check_covariance(C)
    assert res.problem == OC.NEGATIVE_DIAGONAL and res.matrix_66 is None
    assert 'variance [2][2] (z) = -1e-12' in res.detail
    # a zero variance whose row is not zero cannot be a covariance
    C[2, 2] = 0.0
    C[2, 4] = C[4, 2] = 1e-6
    assert OC.check_covariance(C).problem == OC.NOT_PSD


def test_unfilled_conventions_and_non_finite_values():
    assert OC.check_covariance(np.zeros(36)) == OC.CovarianceCheck(None)
    unknown = np.zeros(36)
    unknown[0] = -1.0
    assert OC.check_covariance(unknown) == OC.CovarianceCheck(None)
    unknown[7] = 0.01                   # -1 first and something else: a negative variance, not the convention
    assert OC.check_covariance(unknown).problem == OC.NEGATIVE_DIAGONAL
    C = _correlated(0.0).reshape(-1)
    C[8] = np.inf
    res = OC.check_covariance(C)
    assert res.problem == OC.NOT_FINITE and '[1][2] (y / z) = inf' in res.detail
    with pytest.raises(ValueError):
        OC.check_covariance(np.zeros(35))


# ------------------------------------------------------------------------------------------------------------------
# the twist covariance over a step
# ------------------------------------------------------------------------------------------------------------------
def test_twist_integration_of_a_diff_drive_step_by_hand():
    """A diff-drive base turns 0.3 rad about z while it moves (0.5, 0.1) m in 0.4 s; its twist covariance: forward
    4e-4, sideways 1e-4 m^2/s, yaw 9e-4 rad^2/s. With u = 1 - s/dt, R_bs = Rz(-u theta) and p_bs = -u c (c: the
    chord in b's frame), the integral of Ad Q Ad^T is, entry by entry (S = sin 2theta / 4theta,
    C = (1 - cos 2theta) / 4theta):
      xx = dt [qx (1/2 + S) + qy (1/2 - S) + qw c_y^2 / 3]    yy = dt [qx (1/2 - S) + qy (1/2 + S) + qw c_x^2 / 3]
      xy = dt [-(qx - qy) C - qw c_x c_y / 3]                 yaw = qw dt
      x,yaw = -qw dt c_y / 2                                  y,yaw = qw dt c_x / 2
    and zero elsewhere."""
    qx, qy, qw, theta, dt = 4e-4, 1e-4, 9e-4, 0.3, 0.4
    t_ab = np.array([0.5, 0.1, 0.0])
    Q = np.diag([qx, qy, 0.0, 0.0, 0.0, qw])
    T_ab = _T(t_ab, (0.0, 0.0, theta))
    c = T_ab[:3, :3].T @ t_ab
    S, Cc = math.sin(2 * theta) / (4 * theta), (1 - math.cos(2 * theta)) / (4 * theta)
    want = np.zeros((6, 6))
    want[0, 0] = dt * (qx * (0.5 + S) + qy * (0.5 - S) + qw * c[1] ** 2 / 3)
    want[1, 1] = dt * (qx * (0.5 - S) + qy * (0.5 + S) + qw * c[0] ** 2 / 3)
    want[0, 1] = want[1, 0] = dt * (-(qx - qy) * Cc - qw * c[0] * c[1] / 3)
    want[5, 5] = qw * dt
    want[0, 5] = want[5, 0] = -qw * dt * c[1] / 2
    want[1, 5] = want[5, 1] = qw * dt * c[0] / 2
    got = OC.twist_step_covariance(Q, T_ab, dt)
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-15)
    # per axis (trace / 3 of each block); the mean of the two views' twist covariances is integrated
    sig = PU.twist_sigma(Q * 0.5, Q * 1.5, np.eye(4), T_ab, dt)
    assert sig.rot_rad == pytest.approx(math.sqrt(qw * dt / 3))
    assert sig.trans_m == pytest.approx(math.sqrt((want[0, 0] + want[1, 1]) / 3))
    # the same step in the world: a and b moved and turned together, the answer (in b's frame) is the same
    W = _T((3.0, -1.0, 0.2), (0.1, -0.2, 1.0))
    assert PU.twist_sigma(Q, Q, W, W @ T_ab, dt) == sig


def test_a_straight_step_gains_the_rotation_noise_levered_over_the_rest_of_the_path():
    # 2 m/s forward for 0.25 s, isotropic rotation noise q: lateral variance q L^2 dt / 3 on y and z
    q, dt, L = 1e-3, 0.25, 0.5
    got = OC.twist_step_covariance(np.diag([0, 0, 0, q, q, q]), _T((L, 0, 0)), dt)
    assert got[1, 1] == pytest.approx(q * L ** 2 * dt / 3) and got[2, 2] == pytest.approx(q * L ** 2 * dt / 3)
    assert got[0, 0] == pytest.approx(0.0, abs=1e-18)
    np.testing.assert_allclose(np.diag(got)[3:], [q * dt] * 3)


# ------------------------------------------------------------------------------------------------------------------
# which source: the pose covariance's growth, else the twist covariance, else the drift figures
# ------------------------------------------------------------------------------------------------------------------
def _odom(pose_var, twist_var, stamp):
    pose = None if pose_var is None else np.diag([pose_var[0]] * 3 + [pose_var[1]] * 3)
    twist = None if twist_var is None else np.diag([twist_var[0]] * 3 + [twist_var[1]] * 3)
    return OC.OdometryCovariance(pose, twist, stamp)


def test_the_pose_covariance_is_used_when_it_grows_else_the_twist_else_the_drift():
    chain = [_T(), _T((0.3, 0.0, 0.0), (0.0, 0.0, 0.2))]
    twist = (1e-4, 4e-4)                  # m^2/s, rad^2/s
    grows = PU.odometry_sigma(chain, _odom((1e-4, 1e-6), twist, 10.0), _odom((2e-4, 5e-6), twist, 10.5), 1.0)
    assert grows[1] == PU.GROWTH and grows[0].rot_rad == pytest.approx(2e-3)
    # constant (diff_drive's pose_covariance_diagonal): the twist's, whatever its size
    for pose in ((1e-3, 1e-3), (1e6, 1e6)):
        sig, source = PU.odometry_sigma(chain, _odom(pose, twist, 10.0), _odom(pose, twist, 10.5), 1.0)
        assert source == PU.TWIST and sig.rot_rad == pytest.approx(math.sqrt(4e-4 * 0.5))   # per axis, 0.5 s
    # the rotation grows and the position variance shrinks (the path turned back towards where a heading error
    # began): a growth, its translation the bound of the motion, (1.0 * 0.3)^2 / 3 + 1e-6 * 0.3^2 / 3
    sig, source = PU.odometry_sigma(chain, _odom((2e-4, 1e-6), twist, 10.0), _odom((1e-4, 2e-6), twist, 10.5), 1.0)
    assert source == PU.GROWTH and sig.rot_rad == pytest.approx(1e-3)
    assert sig.trans_m == pytest.approx(math.sqrt(0.3 ** 2 / 3 + 1e-6 * 0.3 ** 2 / 3))
    # only the position grows (an absolute orientation), or both shrink (a correction): not a growth
    assert PU.odometry_sigma(chain, _odom((1e-4, 1e-6), twist, 10.0), _odom((2e-4, 1e-6), twist, 10.5),
                             1.0)[1] == PU.TWIST
    assert PU.odometry_sigma(chain, _odom((2e-4, 5e-6), twist, 10.0), _odom((1e-4, 1e-6), twist, 10.5),
                             1.0)[1] == PU.TWIST
    # given the later one first: read from the earlier stamp on
    assert PU.odometry_sigma(chain[::-1], _odom((2e-4, 5e-6), twist, 10.5), _odom((1e-4, 1e-6), twist, 10.0),
                             1.0)[1] == PU.GROWTH
    # no twist covariance, or no time between the two: the drift figures
    assert PU.odometry_sigma(chain, _odom((1e-3, 1e-3), None, 10.0), _odom((1e-3, 1e-3), None, 10.5), 1.0) == \
        (None, PU.DRIFT)
    assert PU.odometry_sigma(chain, _odom((1e-3, 1e-3), twist, None), _odom((1e-3, 1e-3), twist, 10.5), 1.0) == \
        (None, PU.DRIFT)


def test_a_huge_covariance_makes_a_loose_capped_factor_never_a_stiff_one():
    cfg = PoseRefinerConfig(odom_covariance='odometry')
    odom = {0: _T(), 1: _T((0.05, 0.0, 0.0), (0.0, 0.02, 0.0))}
    cap = (math.radians(cfg.max_jump_rotation_deg), cfg.max_jump_translation_m)

    def steps(a, b):
        return odometry_steps([0, 1], odom, {0: a, 1: b}, cfg)
    # a covariance that jumps to 1e6, or a huge twist covariance (ROS 1 diff_drive's 1e6 on unmeasured axes)
    for a, b, source in ((_odom((1e-4, 1e-6), None, 0.0), _odom((1e6, 1e6), None, 0.1), PUBLISHED),
                         (_odom((1e-3, 1e-3), (1e-3, 1e6), 0.0), _odom((1e-3, 1e-3), (1e-3, 1e6), 0.1), TWIST)):
        s = steps(a, b)
        assert s.source == source and (s.rot_rad, s.trans_m) == pytest.approx(cap)
    # a constant huge covariance without a twist: the drift figures of the step, not the floor
    s = steps(_odom((1e6, 1e6), None, 0.0), _odom((1e6, 1e6), None, 0.1))
    drift = PU.relative_pose_sigma(cfg.drift, [odom[0], odom[1]])
    assert s.source == DRIFT and (s.rot_rad, s.trans_m) == pytest.approx((drift.rot_rad, drift.trans_m))
    assert s.rot_rad > 10 * math.radians(STEP_FLOOR_ROT_DEG)
    # a tiny growth stays at the floor; gtsam order (rotation first)
    C = odometry_step_covariance(odom[0], odom[1], _odom((1e-4, 1e-6), None, 0.0),
                                 _odom((1e-4 + 1e-12, 1e-6 + 1e-14), None, 0.1), cfg)
    np.testing.assert_allclose(np.diag(C), [math.radians(STEP_FLOOR_ROT_DEG) ** 2] * 3 + [STEP_FLOOR_TRANS_M ** 2] * 3)
