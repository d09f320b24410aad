"""The mount and time-offset fit (core.mount_calibration): the distances it scores worked out by hand on one match,
the pose track's interpolation by hand, and the fit on synthetic matches of a camera whose mount is 2 deg and 3 cm
off and whose odometry is stamped 30 ms early (what it recovers, and that its sigmas cover the error), with the
exact mount (nothing found), with a camera that never turns (the shift is not observed) and with too few pairs."""
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dpv_sensor.core.mount_calibration import (MountFitConfig, PairMatchSet, PoseTrack, _Problem, corrected_mount,
                                               fit_mount, normalised_matches)

F_PX = 300.0
K = np.array([[F_PX, 0.0, 320.0], [0.0, F_PX, 240.0], [0.0, 0.0, 1.0]])


def _track(poses_by_t):
    track = PoseTrack()
    for t, T in poses_by_t:
        track.add(t, T)
    return track


def _pose(R=np.eye(3), c=np.zeros(3)):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, c
    return T


def test_the_sampson_distance_of_one_match_by_hand():
    # camera b one metre to the right of a (x axis), no turn: the epipolar lines are the image rows. A match 1 px
    # below its row is 1/sqrt(2) px from the geometry (Sampson splits the error between the two images).
    track = _track([(0.0, _pose()), (1.0, _pose(c=np.array([1.0, 0.0, 0.0])))])
    pair = PairMatchSet(0.0, 1.0, np.array([[0.0, 0.0, 1.0]]), np.array([[-0.2, 1.0 / F_PX, 1.0]]), F_PX)
    prob = _Problem([pair], track)
    d = prob.distances(np.zeros(7), prob.motion(0.0), np.array([True]))
    assert d.shape == (1, 2)
    assert abs(abs(d[0, 0]) - 1.0 / math.sqrt(2.0)) < 1e-9 and d[0, 1] == 0.0
    # on its row it is on the geometry
    pair.xb_n3[0, 1] = 0.0
    assert abs(_Problem([pair], track).distances(np.zeros(7), prob.motion(0.0), np.array([True]))[0, 0]) < 1e-12


def test_a_turn_in_place_is_scored_by_the_rotation_alone():
    # camera b turned 2 deg about y (no move): x_a on the axis lands at x = -tan(2 deg) in b; a match 0.5 px to its
    # right is 0.5 px off, in x only
    R = Rotation.from_euler('y', 2.0, degrees=True).as_matrix()
    track = _track([(0.0, _pose()), (1.0, _pose(R=R))])
    x_b = R.T @ np.array([0.0, 0.0, 1.0])
    x_b = x_b / x_b[2] + np.array([0.5 / F_PX, 0.0, 0.0])
    prob = _Problem([PairMatchSet(0.0, 1.0, np.array([[0.0, 0.0, 1.0]]), x_b[None], F_PX)], track)
    d = prob.distances(np.zeros(7), prob.motion(0.0), np.array([False]))
    assert np.allclose(d, [[-0.5, 0.0]], atol=1e-9)


def test_the_track_interpolates_by_hand():
    R10 = Rotation.from_euler('z', 10.0, degrees=True).as_matrix()
    track = _track([(1.0, _pose()), (2.0, _pose(R=R10, c=np.array([0.2, 0.0, 0.0]))), (4.0, _pose())])
    track.max_gap_s = 1.5
    R, c, ok = track.poses_at(np.array([1.5, 0.5, 2.0, 3.0]))
    assert ok.tolist() == [True, False, True, False]       # before the first; across the 2 s gap
    assert math.isclose(Rotation.from_matrix(R[0]).magnitude(), math.radians(5.0), rel_tol=1e-9)
    assert np.allclose(c[0], [0.1, 0.0, 0.0])
    assert np.allclose(R[2], R10)


def test_the_corrected_mount_is_the_mount_times_the_fit():
    from dpv_sensor.core.mount_calibration import MountFit
    M = _pose(R=Rotation.from_euler('x', 90.0, degrees=True).as_matrix(), c=np.array([0.1, 0.0, 0.2]))
    fit = MountFit(True, rotvec_rad=np.radians([0.0, 0.0, 2.0]), translation_m=np.array([0.01, 0.0, 0.0]),
                   cov_trans_33=np.eye(3) * 1e-6)
    F = _pose(R=Rotation.from_euler('z', 2.0, degrees=True).as_matrix(), c=np.array([0.01, 0.0, 0.0]))
    assert np.allclose(corrected_mount(M, fit), M @ F)
    fit.cov_trans_33 = np.full((3, 3), np.inf)             # a shift not observed is not applied
    assert np.allclose(corrected_mount(M, fit)[:3, 3], M[:3, 3])


# ---------------------------------------------------------------------------------------------- synthetic fits

def _motion(t, turning=True):
    """A handheld-like camera: it turns about all three axes and moves in all three (the node's poses)."""
    a = [0.3 * math.sin(1.3 * t), 0.4 * math.sin(0.9 * t + 1.0), 0.2 * math.sin(1.7 * t + 2.0)]
    a = a if turning else [0.0] * 3
    c = [0.5 * math.sin(0.7 * t), 0.2 * math.sin(1.1 * t + 0.5), 0.4 * math.sin(0.5 * t + 1.0)]
    return _pose(R=Rotation.from_euler('xyz', a).as_matrix(), c=np.array(c))


def _synthetic(E_deg, p_m, dt_s, turning=True, seconds=12.0, noise_px=0.3, seed=0):
    """(pairs, track): the track holds the node's poses at 30 Hz; the images were taken by the camera at
    T(t + dt) F, F = (E, p); each pair's matches are 80 points 1-4 m in front of camera a, seen by both, with
    pixel noise."""
    rng = np.random.default_rng(seed)
    F = _pose(R=Rotation.from_rotvec(np.radians(E_deg)).as_matrix(), c=np.asarray(p_m, float))
    track = _track([(t, _motion(t, turning)) for t in np.arange(0.0, seconds, 1.0 / 30.0)])
    pairs = []
    for ta in np.arange(0.3, seconds - 0.5, 0.15):
        tb = ta + 0.15
        T_a, T_b = _motion(ta + dt_s, turning) @ F, _motion(tb + dt_s, turning) @ F
        px = rng.uniform([0, 0], [640, 480], size=(80, 2))
        rays = np.c_[px, np.ones(80)] @ np.linalg.inv(K).T
        X_a = rays * rng.uniform(1.0, 4.0, size=(80, 1))
        X_b = (np.linalg.inv(T_b) @ T_a @ np.c_[X_a, np.ones(80)].T).T[:, :3]
        pb = (X_b / X_b[:, 2:3]) @ K.T
        pairs.append(normalised_matches(ta, tb, px + rng.normal(0, noise_px, px.shape),
                                        pb[:, :2] + rng.normal(0, noise_px, px.shape), K, 100))
    return pairs, track


def test_the_fit_recovers_a_mount_and_an_offset():
    E_deg, p_m = np.array([1.0, 1.6, 0.6]), np.array([0.03, -0.01, 0.0])
    pairs, track = _synthetic(E_deg, p_m, 0.030)
    fit = fit_mount(pairs, track, MountFitConfig(floor_rot_deg=0.0, floor_trans_m=0.0, floor_time_s=0.0))
    assert fit.ok and fit.pairs == len(pairs)
    e = fit.rotvec_rad - np.radians(E_deg)
    assert math.degrees(float(np.linalg.norm(e))) < 0.1
    assert float(np.linalg.norm(fit.translation_m - p_m)) < 0.005
    assert abs(fit.time_offset_s - 0.030) < 0.002
    # the sigmas cover the errors (sandwich over pairs; no floors here)
    assert float(e @ np.linalg.solve(fit.cov_rot_33, e)) < 16.0
    assert abs(fit.time_offset_s - 0.030) < 4.0 * fit.sigma_time_s
    # and the floors are added in quadrature
    floored = fit_mount(pairs, track)
    assert math.isclose(floored.sigma_time_s ** 2, fit.sigma_time_s ** 2 + 0.001 ** 2, rel_tol=1e-6)
    assert floored.sigma_rot_deg[0] ** 2 == pytest.approx(fit.sigma_rot_deg[0] ** 2 + 0.1 ** 2, rel=1e-6)


def test_the_exact_mount_is_not_confidently_off():
    pairs, track = _synthetic(np.zeros(3), np.zeros(3), 0.0, seed=1)
    fit = fit_mount(pairs, track)
    assert fit.ok
    assert fit.angle_deg < 0.1 and fit.rotation_significance() < 4.0
    assert abs(fit.time_offset_s) < 4.0 * fit.sigma_time_s
    assert float(np.linalg.norm(fit.translation_m)) < 0.005


def test_a_camera_that_never_turns_does_not_show_the_shift():
    pairs, track = _synthetic(np.array([0.0, 2.0, 0.0]), np.array([0.03, 0.0, 0.0]), 0.0, turning=False,
                              seed=2)
    fit = fit_mount(pairs, track, MountFitConfig(max_offset_s=0.0))
    assert fit.ok
    assert not np.all(np.isfinite(fit.sigma_trans_m)) and np.allclose(fit.translation_m, 0.0)
    assert math.isinf(fit.sigma_time_s) and fit.time_offset_s == 0.0
    # the rotation is still seen: the translation directions turn with the mount
    assert abs(math.degrees(fit.rotvec_rad[1]) - 2.0) < 0.15


def test_too_few_pairs_is_no_estimate_with_the_reason():
    pairs, track = _synthetic(np.zeros(3), np.zeros(3), 0.0, seconds=1.5)
    fit = fit_mount(pairs, track, MountFitConfig(min_pairs=len(pairs) + 1))
    assert not fit.ok
    assert fit.reason == f'too few image pairs inside the odometry ({len(pairs)} < {len(pairs) + 1})'
    outside = [PairMatchSet(p.t_a + 100.0, p.t_b + 100.0, p.xa_n3, p.xb_n3, p.focal_px) for p in pairs]
    assert fit_mount(outside, track).reason == 'too few image pairs inside the odometry (0 < 8)'
