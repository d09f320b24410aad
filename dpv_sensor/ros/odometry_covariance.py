"""The odometry's two covariances as the node takes them: each nav_msgs/Odometry's pose and twist covariance checked
(``dpv_sensor.core.odometry_covariance.check_covariance``), kept over time for the images' stamps, and an invalid one
counted under its kind (faults.odometry_covariance_nan, _negative_diagonal, _asymmetric, _not_psd) with a WARN that
names the field, the kind and the offending value, at most once per kind and field every LOG_PERIOD_S. An invalid
covariance is kept as not filled: the relative pose uncertainty then comes from the next source (the pose
covariance's growth, the twist covariance, the drift figures: docs/pose_uncertainty.md)."""
from __future__ import annotations

import time

from dpv_sensor.core.odometry_covariance import ASYMMETRIC, NEGATIVE_DIAGONAL, NOT_FINITE, NOT_PSD
from dpv_sensor.ros import pose_msgs as PM
from dpv_sensor.ros.fault_kinds import (ODOM_COVARIANCE_ASYMMETRIC, ODOM_COVARIANCE_NAN, ODOM_COVARIANCE_NEGATIVE,
                                        ODOM_COVARIANCE_NOT_PSD)
from dpv_sensor.stream.pose_buffer import CovarianceTrack

NS = 1_000_000_000
LOG_PERIOD_S = 30.0
# the check's problem -> (fault kind, what the WARN calls it)
FAULTS = {NOT_FINITE: (ODOM_COVARIANCE_NAN, 'NaN or infinity'),
          NEGATIVE_DIAGONAL: (ODOM_COVARIANCE_NEGATIVE, 'a negative variance'),
          ASYMMETRIC: (ODOM_COVARIANCE_ASYMMETRIC, 'an asymmetric matrix'),
          NOT_PSD: (ODOM_COVARIANCE_NOT_PSD, 'a matrix that is not positive semi-definite')}


def instead_text(field: str, pose_uncertainty: str) -> str:
    """What the node does instead of using an invalid covariance of `field` ('pose' or 'twist')."""
    if pose_uncertainty not in ('covariance', 'auto'):
        return f'pose_uncertainty {pose_uncertainty} does not read it'
    other = ('the twist covariance where it is filled' if field == 'pose'
             else "the pose covariance's growth where it grows")
    exact = ('; the measurement counts the poses as exact without either (pose_uncertainty covariance)'
             if pose_uncertainty == 'covariance' else '')
    return f'the relative pose uncertainty comes from {other}, else from the drift figures (odom_drift_*){exact}'


class OdometryCovariances:
    """The pose and twist covariance tracks (``pose``, ``twist``: 6x6 per odometry stamp, None where not filled or
    invalid) and the faults of the invalid ones. `faults`: the node's FaultLog; `pose_uncertainty()`: the setting,
    read at each fault (for the WARN's wording)."""

    def __init__(self, faults, pose_uncertainty):
        self.faults = faults
        self._mode = pose_uncertainty
        self.pose = CovarianceTrack()
        self.twist = CovarianceTrack()
        self._logged: dict[tuple[str, str], float] = {}

    def add(self, msg, stamp_ns: int) -> None:
        """Check a nav_msgs/Odometry's two covariances and keep them at `stamp_ns` (an invalid one as not filled)."""
        for field, check, track in zip(('pose', 'twist'), PM.odometry_covariance_checks(msg), (self.pose, self.twist)):
            track.add(stamp_ns, check.matrix_66)
            if check.problem is not None:
                self._fault(field, check, stamp_ns)

    def _fault(self, field: str, check, stamp_ns: int) -> None:
        kind, what = FAULTS[check.problem]
        now = time.monotonic()
        last = self._logged.get((kind, field))
        if last is not None and now - last < LOG_PERIOD_S:
            self.faults.count(kind)
            return
        self._logged[(kind, field)] = now
        self.faults.report(kind, f'odometry at {stamp_ns / NS:.3f} s has {what} in its {field} covariance: the '
                           f'covariance is ignored and {instead_text(field, self._mode())}; {check.detail} '
                           f'(faults.{kind} counts them; logged at most every {LOG_PERIOD_S:g} s)',
                           key=f'{kind}:{field}')
