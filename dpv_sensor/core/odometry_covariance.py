"""What a nav_msgs/Odometry's two covariances say, checked, and the twist covariance integrated over an interval.

**Validation** (:func:`check_covariance`). A 6x6 covariance (ROS order: x, y, z, then rotation about x, y, z) is used
only when it is a covariance. In this order, the first failing rule names the fault:

1. ``not_finite``: NaN or infinity anywhere.
2. not filled (no fault, treated as absent): all zeros, or -1 in its first element and zeros elsewhere (the "no
   estimate" convention of sensor_msgs).
3. ``negative_diagonal``: a variance below zero (a zero variance is allowed: an axis a planar robot does not move
   in, or calls exact).
4. ``asymmetric``: ``|C_ij - C_ji| > SYMMETRY_TOL * sqrt(C_ii C_jj)`` for some i, j (the tolerance in units of the
   two variances, so metres and radians mix).
5. ``not_psd``: the smallest eigenvalue of the correlation-scaled matrix ``D^-1/2 C D^-1/2`` (``D`` its diagonal)
   below ``-PSD_TOL``: no distribution has it.

A covariance that passes is returned symmetrised; one that fails is treated as not filled by the callers (the next
source of the pose uncertainty is used) and the node counts and logs the fault.

**The twist covariance over an interval** (:func:`twist_step_covariance`). ``twist.covariance`` is given in the
odometry's child frame (the robot's base) and describes a velocity. It is read as a *rate*: the white-noise density
of the velocity error, the variance the relative pose gains per second of motion (m^2/s and rad^2/s; over ``dt``
seconds the error of a straight motion without rotation grows by ``Q dt``). A velocity error ``e(s) ds`` at time
``s`` of the interval ``[0, dt]`` from pose a to pose b perturbs the motion there, in the body frame of that moment:
``T_ab' = T_as exp(e ds) T_sb = T_ab exp(Ad(T_bs) e ds)``, so the error of the relative pose in b's frame (right
perturbation, as a between factor measures it) is ``delta = int Ad(T_bs) e(s) ds`` and

    Sigma_ab = int_0^dt Ad(T_bs) Q Ad(T_bs)^T ds,      Ad(R, p) = [[R, [p]x R], [0, R]]   (order: v, w)

The adjoint turns the body-frame errors into b's frame (``R``) and adds the lever of a rotation error at ``s`` over
the rest of the path (``[p]x``: a heading error rotates everything travelled after it). The motion between a and b
is taken as the pose buffer interpolates it (SLERP + linear): with ``u = 1 - s / dt``, ``R_bs = exp(-u log R_ab)``
and ``p_bs = -u R_ab^T t_ab``. The integral is evaluated by Gauss-Legendre quadrature in ``u``. For a straight
motion of length ``L`` and an isotropic rotation density ``q_w`` this gives the familiar lateral term
``q_w L^2 dt / 3`` on top of ``Q_v dt``.

numpy only; no ROS.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = ['NOT_FINITE', 'NEGATIVE_DIAGONAL', 'ASYMMETRIC', 'NOT_PSD', 'PROBLEMS', 'SYMMETRY_TOL', 'PSD_TOL',
           'CovarianceCheck', 'check_covariance', 'OdometryCovariance', 'twist_step_covariance', 'adjoint']

NOT_FINITE, NEGATIVE_DIAGONAL, ASYMMETRIC, NOT_PSD = 'not_finite', 'negative_diagonal', 'asymmetric', 'not_psd'
PROBLEMS = (NOT_FINITE, NEGATIVE_DIAGONAL, ASYMMETRIC, NOT_PSD)
# tolerances in correlation units (each entry divided by the square roots of its two variances): well above the
# rounding of a covariance computed in float32 and copied into the message's float64 (~1e-7), far below any real
# fault (a sign error, a transposed block, a variance written into a covariance's place)
SYMMETRY_TOL = 1e-5
PSD_TOL = 1e-5
AXES = ('x', 'y', 'z', 'rotation about x', 'rotation about y', 'rotation about z')
_QUADRATURE = np.polynomial.legendre.leggauss(12)


@dataclass(frozen=True)
class CovarianceCheck:
    """The outcome of :func:`check_covariance`: the usable 6x6 (symmetrised; None when not filled or invalid), the
    fault (one of :data:`PROBLEMS`, None when there is none) and the offending value in words."""
    matrix_66: Optional[np.ndarray]
    problem: Optional[str] = None
    detail: str = ''


def _entry(i: int, j: int) -> str:
    return f'[{i}][{j}] ({AXES[i]} / {AXES[j]})' if i != j else f'[{i}][{i}] ({AXES[i]})'


def check_covariance(values) -> CovarianceCheck:
    """Check a covariance of 36 values (row-major 6x6, as nav_msgs carries it) against the rules of the module
    docstring; ValueError for another number of values."""
    C = np.asarray(values, dtype=np.float64).reshape(-1)
    if C.size != 36:
        raise ValueError(f'a covariance has 36 values, got {C.size}')
    C = C.reshape(6, 6)
    bad = np.argwhere(~np.isfinite(C))
    if bad.size:
        i, j = (int(v) for v in bad[0])
        return CovarianceCheck(None, NOT_FINITE, f'{_entry(i, j)} = {C[i, j]}')
    if not np.any(C) or (C[0, 0] == -1.0 and np.count_nonzero(C) == 1):
        return CovarianceCheck(None)
    d = np.diag(C)
    if np.any(d < 0):
        i = int(np.argmin(d))
        return CovarianceCheck(None, NEGATIVE_DIAGONAL, f'variance {_entry(i, i)} = {d[i]:.6g}')
    # correlation scaling; a zero variance gets a floor far below the others (its row must then be ~0 to pass)
    s = np.sqrt(np.maximum(d, 1e-12 * float(d.max())))
    scale = np.outer(s, s)
    asym = np.abs(C - C.T) / scale
    if float(asym.max()) > SYMMETRY_TOL:
        i, j = (int(v) for v in np.unravel_index(int(np.argmax(asym)), asym.shape))
        return CovarianceCheck(None, ASYMMETRIC, f'{_entry(i, j)} = {C[i, j]:.6g} but {_entry(j, i)} = '
                               f'{C[j, i]:.6g} (difference {asym[i, j]:.3g} of sqrt(C_ii C_jj), tolerance '
                               f'{SYMMETRY_TOL:g})')
    S = 0.5 * (C + C.T)
    lam = float(np.linalg.eigvalsh(S / scale)[0])
    if lam < -PSD_TOL:
        return CovarianceCheck(None, NOT_PSD, f'smallest eigenvalue of the correlation-scaled matrix {lam:.3g} '
                               f'(tolerance {-PSD_TOL:g})')
    return CovarianceCheck(S)


@dataclass(frozen=True)
class OdometryCovariance:
    """What the odometry says about itself at one pose: its pose covariance (6x6, ROS order, in the odometry frame),
    its twist covariance (6x6, ROS order, in the child frame, read as a rate: module docstring) and the stamp (s);
    each None when not filled. :meth:`of` also takes a bare pose covariance."""
    pose_66: Optional[np.ndarray] = None
    twist_66: Optional[np.ndarray] = None
    stamp: Optional[float] = None

    @classmethod
    def of(cls, value) -> Optional['OdometryCovariance']:
        """An OdometryCovariance from itself, a bare 6x6 pose covariance, or None (None)."""
        if value is None or isinstance(value, cls):
            return value
        return cls(pose_66=np.asarray(value, np.float64).reshape(6, 6))


def _hat(v) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def adjoint(R_33: np.ndarray, p_3: np.ndarray) -> np.ndarray:
    """The 6x6 adjoint of the pose (R, p) acting on twists in ROS order (linear, angular)."""
    A = np.zeros((6, 6))
    A[:3, :3] = R_33
    A[3:, 3:] = R_33
    A[:3, 3:] = _hat(p_3) @ R_33
    return A


def twist_step_covariance(Q_66: np.ndarray, T_a_b_44: np.ndarray, dt: float) -> np.ndarray:
    """Covariance (6x6, ROS order, in b's frame) of the relative pose ``T_a_b`` accumulated from a twist covariance
    ``Q_66`` (child frame, per second) over ``dt`` seconds of the motion from a to b (module docstring)."""
    dt = float(dt)
    if not (dt >= 0 and math.isfinite(dt)):
        raise ValueError(f'dt must be finite and >= 0, got {dt}')
    Q = np.asarray(Q_66, np.float64).reshape(6, 6)
    T = np.asarray(T_a_b_44, np.float64)
    rotvec = Rotation.from_matrix(T[:3, :3]).as_rotvec()
    chord_b = T[:3, :3].T @ T[:3, 3]                      # t_ab in b's frame
    nodes, weights = _QUADRATURE
    out = np.zeros((6, 6))
    for x, w in zip(nodes, weights):
        u = 0.5 * (x + 1.0)                               # [-1, 1] -> [0, 1]
        A = adjoint(Rotation.from_rotvec(-u * rotvec).as_matrix(), -u * chord_b)
        out += 0.5 * w * (A @ Q @ A.T)
    return dt * 0.5 * (out + out.T)
