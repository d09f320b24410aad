"""The pose-error oracle of studies.pose_error_depth: the error scaling, the split of a rotation error about the
epipolar axis, and the oracle refiner's poses worked out by hand on tiny cases."""
import math
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dpv_sensor.studies import pose_error_depth as PED


def _pose(rotvec_deg, t):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
    T[:3, 3] = t
    return T


def test_scale_error_ends_and_middle():
    true = _pose([0, 5, 0], [0.1, 0, 0])
    est = true @ _pose([0.4, 0, 0], [0, 0.02, 0])          # an error of 0.4 deg about x and 2 cm along y
    assert np.allclose(PED.scale_error(true, est, 0, 0), true)
    assert np.allclose(PED.scale_error(true, est, 1, 1), est)
    half = np.linalg.inv(true) @ PED.scale_error(true, est, 0.5, 0.25)
    assert np.allclose(half, _pose([0.2, 0, 0], [0, 0.005, 0]))


def test_rotation_error_parts_about_the_epipolar_axis():
    # baseline along x: t x z = -y, so a turn about y slides the image along the (horizontal) epipolar lines
    true = _pose([0, 0, 0], [0.1, 0, 0])
    total, along, across = PED.rotation_error_parts(true, _pose([0, 0.3, 0], [0.1, 0, 0]))
    assert (total, along, across) == pytest.approx((0.3, 0.3, 0.0), abs=1e-9)
    total, along, across = PED.rotation_error_parts(true, _pose([0.3, 0, 0.4], [0.1, 0, 0]))
    assert (total, along, across) == pytest.approx((0.5, 0.0, 0.5), abs=1e-9)
    # a baseline along the optical axis has no epipolar direction to slide along
    assert PED.rotation_error_parts(_pose([0, 0, 0], [0, 0, 0.1]), _pose([0, 0.3, 0], [0, 0, 0.1]))[1] == 0.0


def _window():
    gt = {0.0: _pose([0, 0, 0], [0, 0, 0]), 1.0: _pose([0, 2, 0], [0.05, 0, 0]), 2.0: _pose([1, 4, 0], [0.1, 0, 0])}
    odo = {s: T @ _pose([0.2 * s, -0.1 * s, 0.3], [0.01 * s, 0, 0]) for s, T in gt.items()}
    kfs = [SimpleNamespace(stamp=s, odom_T_world_cam_44=odo[s], T_world_cam_44=odo[s].copy()) for s in gt]
    return gt, odo, SimpleNamespace(keyframes=kfs, reference=1)


def test_oracle_gives_the_truth_relative_to_the_reference_at_zero_and_the_odometry_at_one():
    gt, odo, req = _window()
    zero = PED.ScaledErrorRefiner(gt.__getitem__, 0, 0)(req)
    one = PED.ScaledErrorRefiner(gt.__getitem__, 1, 1)(req)
    assert np.allclose(zero[1], odo[1]) and np.allclose(one[1], odo[1])   # the reference keeps its odometry pose
    for i, s in ((0, 0.0), (2, 2.0)):
        assert np.allclose(np.linalg.inv(zero[i]) @ zero[1], np.linalg.inv(gt[s]) @ gt[1.0])
        assert np.allclose(np.linalg.inv(one[i]) @ one[1], np.linalg.inv(odo[s]) @ odo[1.0])


def test_error_log_records_what_the_sweep_gets_and_the_odometry():
    gt, odo, req = _window()
    log = PED.ErrorLog(PED.ScaledErrorRefiner(gt.__getitem__, 0.5, 1), gt.__getitem__)
    log(req)
    assert len(log.rows) == 2                                  # the two sources, not the reference
    m = log.means()
    assert m['rot'] == pytest.approx(0.5 * m['odo_rot'], rel=1e-6)
    assert math.isfinite(m['rot_along']) and m['rot_along'] <= m['rot'] + 1e-12
    # no refiner: the sweep gets the odometry
    plain = PED.ErrorLog(None, gt.__getitem__)
    assert plain(req) is None
    assert plain.means()['rot'] == pytest.approx(plain.means()['odo_rot'])
    with pytest.raises(AttributeError):
        plain.tracking_lost                                    # noqa: B018  delegated to the (absent) refiner


def test_cli_names_a_missing_folder_or_a_bad_scale(tmp_path, capsys):
    (tmp_path / 'seq').mkdir()
    for name in ('poses.txt', 'K.txt'):
        (tmp_path / 'seq' / name).write_text('')
    with pytest.raises(SystemExit) as e:
        PED.main(['--data', str(tmp_path), '--sequences', 'other'])
    assert e.value.code == 2 and "no sequence folder 'other'" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        PED.main(['--data', str(tmp_path / 'none')])
    assert 'not a folder' in capsys.readouterr().err
    with pytest.raises(SystemExit):
        PED.main(['--data', str(tmp_path), '--scales', 'half'])
    assert "--scales 'half'" in capsys.readouterr().err
