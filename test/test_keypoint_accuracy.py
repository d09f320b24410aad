"""studies.keypoint_accuracy: the error of a keypoint estimate against the truth in its covariance's
coordinates, the rotation given the direction, and the floors fitted to honest NEES."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from dpv_sensor.studies import keypoint_accuracy as KA
from dpv_sensor.core.keypoint_pose import KeypointPose


def _pair(err, cov=None):
    cov = np.eye(len(err)) * 1e-12 if cov is None else cov
    return KA.PairError('s', 1, 0, 50, 5.0, 0.05, list(err), np.asarray(cov).tolist())


def test_pair_error_is_the_left_rotation_increment_and_the_direction_increment():
    R_gt = cv2.Rodrigues(np.array([[0.1], [-0.2], [0.05]]))[0]
    t_gt = np.array([0.03, -0.01, 0.04])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R_gt, t_gt
    delta = np.radians([0.3, -0.2, 0.1])
    R_kp = cv2.Rodrigues(delta.reshape(3, 1))[0] @ R_gt               # the estimate: Exp(delta) R_true
    u = t_gt / np.linalg.norm(t_gt)
    off = np.cross(u, [0.0, 0.0, 1.0])
    t_kp = u + 0.01 * off / np.linalg.norm(off)
    t_kp /= np.linalg.norm(t_kp)
    B = np.c_[off / np.linalg.norm(off), np.cross(t_kp, off / np.linalg.norm(off))]   # normal to t_kp (to first order)
    kp = KeypointPose(True, None, R_kp, t_kp, 50, 60, 5.0, 0.01, 0.1, np.eye(5) * 1e-6, B)
    e = KA.pair_error('s', 1, 0, kp, T)
    np.testing.assert_allclose(e.err[:3], delta, atol=1e-12)
    np.testing.assert_allclose(e.err[3:], B.T @ (t_kp - u), atol=1e-12)
    assert abs(e.err[3]) == pytest.approx(0.01, rel=1e-3) and abs(e.err[4]) < 1e-4
    assert e.has_direction and e.baseline_m == pytest.approx(np.linalg.norm(t_gt))


def test_rotation_given_the_direction_by_hand():
    # rotation x and direction x perfectly explained by each other (corr 0.8): given the direction, the rotation's
    # x error is d_r - (0.8 * 1 * 2 / 2^2) d_d and its variance 1 - 0.64
    S = np.diag([1.0, 1.0, 1.0, 4.0, 4.0])
    S[0, 3] = S[3, 0] = 0.8 * 1.0 * 2.0
    rot, dirn, cond = KA.blocks(_pair([0.5, 0.0, 0.0, 1.0, 0.0], S))
    np.testing.assert_allclose(cond[0], [0.5 - 0.4 * 1.0, 0.0, 0.0])
    assert cond[1][0, 0] == pytest.approx(1 - 0.64)
    assert KA.nees(*dirn) == pytest.approx(1.0 / 4.0)
    assert KA.nees(*rot) == pytest.approx(0.25)
    assert KA.nees([1.0, 0.0], np.zeros((2, 2))) == math.inf                 # a covariance that calls it exact
    # floors add in quadrature before conditioning: a huge direction floor leaves the rotation's marginal
    _, _, cond_floor = KA.blocks(_pair([0.5, 0.0, 0.0, 1.0, 0.0], S), 0.0, math.degrees(1e4))
    assert cond_floor[1][0, 0] == pytest.approx(1.0, rel=1e-6)


def test_fitted_floors_make_the_median_nees_honest_and_ignore_gross_errors():
    rng = np.random.default_rng(0)
    rows = [_pair(np.r_[rng.normal(0, math.radians(0.3), 3), rng.normal(0, math.radians(3.0), 2)])
            for _ in range(400)]
    br, bd = KA.fit_floors(rows)
    assert br == pytest.approx(0.3, rel=0.15) and bd == pytest.approx(3.0, rel=0.15)
    rows += [_pair(np.r_[rng.normal(0, math.radians(3.0), 3), rng.normal(0, math.radians(40.0), 2)])
             for _ in range(40)]                                          # 10 % matched one period off
    br2, bd2 = KA.fit_floors(rows)
    assert br2 == pytest.approx(0.3, rel=0.25) and bd2 == pytest.approx(3.0, rel=0.25)
    assert KA.fit_floors([_pair([0.0, 0.0, 0.0])]) == (0.0, 0.0)       # no pair with a direction: nothing to fit


@pytest.fixture(scope='module')
def sift_run(tmp_path_factory):
    """The tool on rendered seed 7 (40 frames) with its default detector, SIFT: (printed text, JSON). One run for
    the two tests below that read it (the detector test compares ORB with it)."""
    import contextlib
    import io
    import json
    out = tmp_path_factory.mktemp('kp') / 'kp.json'
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = KA.main(['--seeds', '7', '--frames', '40', '--json', str(out)])
    assert code == 0
    return buf.getvalue(), json.loads(out.read_text())


def test_the_tool_measures_a_rendered_scene(sift_run):
    text, data = sift_run
    assert 'synthetic_seed7' in text and 'floors fitted on the rendered sequences' in text
    pairs = [KA.PairError(**p) for p in data['pairs']]
    assert len(pairs) >= 5 and all(p.sequence == 'synthetic_seed7' for p in pairs)
    assert sum(p.ref > p.src for p in pairs) == len(pairs)                  # each keyframe with earlier ones
    rot_deg = np.degrees([np.linalg.norm(p.err[:3]) for p in pairs])
    assert np.median(rot_deg) < 2.0                                          # keypoints, not noise
    assert data['tried']['synthetic_seed7'] >= len(pairs)


def test_the_tool_measures_the_detector_it_is_given(sift_run, tmp_path, capsys):
    """--detector orb matches ORB keypoints (other pairs and inlier counts than SIFT's, the default, on the same
    scene)."""
    import json
    runs = {'sift': sift_run[1]}
    out = tmp_path / 'orb.json'
    assert KA.main(['--seeds', '7', '--frames', '40', '--detector', 'orb', '--json', str(out)]) == 0
    runs['orb'] = json.loads(out.read_text())
    for det in ('sift', 'orb'):
        assert runs[det]['detector'] == det
    inliers = {d: [(p['ref'], p['src'], p['inliers']) for p in r['pairs']] for d, r in runs.items()}
    assert inliers['orb'] and inliers['orb'] != inliers['sift']


def test_the_tool_measures_the_flow_rotations_and_fits_their_covariance_scale(tmp_path, capsys):
    """--matcher flow: 3-dof rotation errors (given the true direction) of the window's flow factors, and the
    covariance_scale that makes the rendered scene's median NEES the honest 2.37."""
    import json
    out = tmp_path / 'flow.json'
    assert KA.main(['--seeds', '7', '--frames', '40', '--matcher', 'flow', '--json', str(out)]) == 0
    text = capsys.readouterr().out
    assert 'Flow rotation given the true direction' in text and 'covariance_scale that gives' in text
    data = json.loads(out.read_text())
    pairs = [KA.PairError(**p) for p in data['pairs']]
    assert len(pairs) >= 5 and all(len(p.err) == 3 and np.shape(p.cov) == (3, 3) for p in pairs)
    assert np.median(np.degrees([np.linalg.norm(p.err) for p in pairs])) < 0.3     # started 0.5 deg off
    nees = np.median([KA.nees(p.err, p.cov) for p in pairs])
    assert data['fitted_covariance_scale'] == pytest.approx(data['covariance_scale'] * nees / 2.366, rel=1e-6)
