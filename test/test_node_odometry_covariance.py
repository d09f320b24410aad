"""Odometry covariances through the node process: every invalid kind of pose or twist covariance is counted under its
own faults.* key and logged once per kind and field, naming the value; covariances just inside each tolerance are not
counted. (Which source the window's odometry factors use, as /diagnostics reports it: test_node_pose_uncertainty.)"""
import numpy as np

from stream_driver import FAST_PARAMS, StreamDriver, params_args
from dpv_sensor.core.odometry_covariance import PSD_TOL, SYMMETRY_TOL
from dpv_sensor.ros import pose_msgs as PM

REMAPS = {'image': '/cam/image', 'camera_info': '/cam/camera_info', 'odom': '/odom'}
STD = np.array([0.02, 0.01, 0.05, 0.002, 0.004, 0.03])       # m, m, m, rad, rad, rad


def _cov(rho=0.0, i=0, j=5):
    R = np.eye(6)
    R[i, j] = R[j, i] = rho
    return R * np.outer(STD, STD)


def _asymmetric(factor):
    C = _cov(0.3)
    C[5, 0] += factor * SYMMETRY_TOL * STD[0] * STD[5]
    return C


def _negative(k):
    C = _cov()
    C[k, k] = -1e-12
    return C


def _planar():
    C = _cov()
    C[2, 2] = 0.0                  # z exact: allowed
    return C


NAN = _cov()
NAN[1, 1] = np.nan
# per image index: (pose covariance, twist covariance) of an extra odometry message 1 ms before the image
CASES = {2: (NAN, None),
         3: (_negative(2), None),
         4: (None, _asymmetric(1.1)),
         5: (None, _cov(-(1.0 + 1.1 * PSD_TOL), 1, 3)),
         6: (_asymmetric(0.9), _cov(-(1.0 + 0.9 * PSD_TOL), 1, 3)),       # just inside both tolerances
         7: (_planar(), _planar()),
         8: (None, _negative(5)),
         9: (_negative(0), None)}


def test_each_invalid_covariance_kind_is_counted_and_logged_once_per_kind_and_field():
    drv = StreamDriver(params_args(FAST_PARAMS, REMAPS), topics=REMAPS, frames=12, name='odometry_covariances')
    try:
        drv.wait_ready()
        for i in range(12):
            stamp = drv.stamp_ns(i)
            if i in CASES:
                pose, twist = CASES[i]
                drv.pubs['odom'].publish(PM.matrix_to_odometry(drv.seq.pose(i), stamp - 1_000_000, 'base_link',
                                                              'odom', pose_covariance_66=pose,
                                                              twist_covariance_66=twist))
            drv.send(i, stamp)
            assert drv.wait_accounted(i + 1), drv.outputs.diagnostics
        diag = drv.wait_diagnostics()
    finally:
        log = drv.stop()
    assert drv.code == 0, log
    counts = {k: int(diag.get(f'faults.odometry_covariance_{k}', 0))
              for k in ('nan', 'negative_diagonal', 'asymmetric', 'not_psd')}
    assert counts == {'nan': 1, 'negative_diagonal': 3, 'asymmetric': 1, 'not_psd': 1}, diag
    drops = {k: v for k, v in diag.items() if k.startswith(('dropped.', 'lost.'))}
    assert int(diag['frames_processed']) == 12, drops       # the images are not affected
    assert 'NaN or infinity in its pose covariance: the covariance is ignored' in log, log
    assert '[1][1] (y) = nan' in log, log
    assert 'a negative variance in its pose covariance' in log and 'variance [2][2] (z) = -1e-12' in log, log
    assert 'a negative variance in its twist covariance' in log and '[5][5] (rotation about z)' in log, log
    # the pose's second negative variance (image 9) is counted, not logged again
    assert log.count('a negative variance in its pose covariance') == 1, log
    assert 'an asymmetric matrix in its twist covariance' in log and '[5][0] (rotation about z / x)' in log, log
    assert 'a matrix that is not positive semi-definite in its twist covariance' in log, log
    assert 'asymmetric matrix in its pose' not in log and 'semi-definite in its pose' not in log, log
