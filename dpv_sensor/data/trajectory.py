"""Smooth hand-held camera trajectories for the synthetic renderer (numpy only).

A :class:`HandheldTrajectory` walks along a smooth closed loop (a randomly deformed ellipse in the
horizontal plane with a gently varying height) at a smoothly varying walking speed, with a small hand
shake on top. The viewing direction is the walking direction turned by a slowly drifting yaw offset
(mostly towards the inside of the loop, so the camera looks across the room — a drifting look-at target),
plus a drifting pitch, a small roll and a small rotational tremor. Everything is a closed-form function of
time (sums of sinusoids and an arc-length table), so the pose at any time — sub-frame times for motion
blur and rolling shutter included — is exact and deterministic.

World frame: z up. Camera frame: OpenCV (x right, y down, z forward). ``pose(t)`` returns T_world_cam.

:func:`corrupt_trajectory` turns an exact trajectory into an odometry-like one (drift and rotation noise per
step), for pose-refinement experiments and as training augmentation; :func:`corruption_variance` and
:func:`corruption_twist_variance` are what an honest odometry would publish for that noise as its pose and its twist
covariance.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import List, Sequence, Tuple

import numpy as np
from scipy.spatial.transform import Rotation


def _sines(terms: Sequence[Tuple[float, float, float]], t: np.ndarray) -> np.ndarray:
    """sum_k a_k sin(w_k t + p_k) for terms (a, w, p)."""
    out = np.zeros_like(t, dtype=np.float64)
    for a, w, p in terms:
        out += a * np.sin(w * t + p)
    return out


def _sines_integral(terms: Sequence[Tuple[float, float, float]], t: np.ndarray) -> np.ndarray:
    """Integral from 0 of sum_k a_k sin(w_k s + p_k) ds."""
    out = np.zeros_like(t, dtype=np.float64)
    for a, w, p in terms:
        out += a / w * (np.cos(p) - np.cos(w * t + p))
    return out


def rotation_from_ypr(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """(..., 3, 3) R_world_cam for a camera with OpenCV axes in a z-up world.

    yaw: heading of the optical axis in the horizontal plane (0 = +x, pi/2 = +y); pitch: elevation of the
    optical axis (positive = looking up); roll: rotation about the optical axis (positive turns the image
    x axis towards the image y axis).
    """
    yaw, pitch, roll = np.broadcast_arrays(np.asarray(yaw, np.float64), np.asarray(pitch, np.float64),
                                           np.asarray(roll, np.float64))
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    forward = np.stack([cp * cy, cp * sy, sp], axis=-1)
    right = np.stack([sy, -cy, np.zeros_like(yaw)], axis=-1)
    down = np.cross(forward, right)
    cr, sr = np.cos(roll)[..., None], np.sin(roll)[..., None]
    right_r = cr * right + sr * down
    down_r = -sr * right + cr * down
    return np.stack([right_r, down_r, forward], axis=-1)


@dataclass
class HandheldTrajectory:
    """A closed-loop hand-held walk; all angles in radians, lengths in metres, times in seconds.

    The loop is ``center + [ax * r(phi) cos(phi), ay * r(phi) sin(phi)]`` with
    ``r(phi) = 1 + sum_k a_k cos(k phi + p_k)`` and height ``h0 + sum_k b_k sin(k phi + q_k)``.
    """
    center: Tuple[float, float]
    ax: float
    ay: float
    radial_terms: List[Tuple[int, float, float]]       # (k, amplitude, phase)
    height0: float
    height_terms: List[Tuple[int, float, float]]       # (k, amplitude, phase)
    direction: int                                     # +1 counter-clockwise, -1 clockwise
    speed_mean: float
    speed_terms: List[Tuple[float, float, float]]      # (amplitude m/s, omega, phase)
    t0: float                                          # time offset (start point on the loop)
    shake_terms: List[Tuple[Tuple[float, float, float], float, Tuple[float, float, float]]]
    yaw_offset_mean: float
    yaw_terms: List[Tuple[float, float, float]]
    pitch_mean: float
    pitch_terms: List[Tuple[float, float, float]]
    roll_terms: List[Tuple[float, float, float]]
    samples_per_loop: int = 4096
    _table: Tuple[np.ndarray, np.ndarray] = field(default=None, init=False, repr=False)

    # -- loop geometry -----------------------------------------------------------------------------
    def loop_points(self, phi: np.ndarray) -> np.ndarray:
        """(..., 3) points of the loop (without hand shake) at loop angles phi."""
        phi = np.asarray(phi, dtype=np.float64)
        z = np.full_like(phi, self.height0)
        for k, b, q in self.height_terms:
            z = z + b * np.sin(k * phi + q)
        return np.concatenate([self._loop_xy(phi), z[..., None]], axis=-1)

    def _loop_xy(self, phi: np.ndarray) -> np.ndarray:
        """(..., 2) horizontal projection of the loop at loop angles phi."""
        r = np.ones_like(phi)
        for k, a, p in self.radial_terms:
            r = r + a * np.cos(k * phi + p)
        return np.stack([self.center[0] + self.ax * r * np.cos(phi), self.center[1] + self.ay * r * np.sin(phi)],
                        axis=-1)

    def _arc_table(self) -> Tuple[np.ndarray, np.ndarray]:
        if self._table is None:
            phi = np.linspace(0.0, 2 * math.pi, self.samples_per_loop + 1)
            pts = self.loop_points(phi)
            seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
            self._table = (phi, np.concatenate([[0.0], np.cumsum(seg)]))
        return self._table

    @property
    def loop_length(self) -> float:
        return float(self._arc_table()[1][-1])

    @property
    def shake_bound(self) -> float:
        """Upper bound on the distance between the camera centre and the loop (hand shake)."""
        return float(sum(np.linalg.norm(a) for a, _, _ in self.shake_terms))

    @property
    def speed_range(self) -> Tuple[float, float]:
        """Bounds of the walking speed along the loop (m/s), hand shake excluded."""
        amp = sum(abs(a) for a, _, _ in self.speed_terms)
        return self.speed_mean - amp, self.speed_mean + amp

    def max_curvature(self) -> float:
        """Largest curvature (1/m) of the loop's horizontal projection."""
        phi = np.linspace(0.0, 2 * math.pi, 4096, endpoint=False)
        h = phi[1] - phi[0]
        p0 = self._loop_xy(phi)                   # the loop is periodic: the neighbours at +-h are the grid's
        pp = np.roll(p0, -1, axis=0)
        pm = np.roll(p0, 1, axis=0)
        d1 = (pp - pm) / (2 * h)
        d2 = (pp - 2 * p0 + pm) / (h * h)
        cross = np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])
        return float(np.max(cross / np.maximum(np.linalg.norm(d1, axis=1), 1e-12) ** 3))

    def max_turn_rate(self) -> float:
        """Upper bound (rad/s) of the walking direction's turn rate: max speed x max curvature."""
        return self.speed_range[1] * self.max_curvature()

    def dense_loop(self, spacing: float = 0.01) -> np.ndarray:
        """(M, 3) loop points at most ``spacing`` apart (for clearance checks)."""
        n = max(64, int(math.ceil(self.loop_length / spacing)))
        return self.loop_points(np.linspace(0.0, 2 * math.pi, n, endpoint=False))

    # -- time parametrisation ----------------------------------------------------------------------
    def arc_length(self, t: np.ndarray) -> np.ndarray:
        tau = np.asarray(t, dtype=np.float64) + self.t0
        return self.speed_mean * tau + _sines_integral(self.speed_terms, tau)

    def loop_angle(self, t: np.ndarray) -> np.ndarray:
        phi_tab, s_tab = self._arc_table()
        s = np.mod(self.arc_length(t), s_tab[-1])
        if self.direction < 0:          # walk the loop backwards at the same speed
            s = s_tab[-1] - s
        return np.interp(s, s_tab, phi_tab)

    def position(self, t: np.ndarray) -> np.ndarray:
        """(..., 3) camera centre in the world at times t."""
        t = np.asarray(t, dtype=np.float64)
        p = self.loop_points(self.loop_angle(t))
        for amp, w, ph in self.shake_terms:
            p = p + np.asarray(amp) * np.sin(w * (t[..., None] + self.t0) + np.asarray(ph))
        return p

    def heading(self, t: np.ndarray) -> np.ndarray:
        """Walking direction (yaw of the loop tangent, radians) at times t."""
        phi = self.loop_angle(t)
        eps = 1e-4
        d = self.loop_points(phi + eps) - self.loop_points(phi - eps)
        d = d * self.direction
        return np.arctan2(d[..., 1], d[..., 0])

    def rotation(self, t: np.ndarray) -> np.ndarray:
        """(..., 3, 3) R_world_cam at times t."""
        t = np.asarray(t, dtype=np.float64)
        tau = t + self.t0
        yaw = self.heading(t) + self.yaw_offset_mean + _sines(self.yaw_terms, tau)
        pitch = self.pitch_mean + _sines(self.pitch_terms, tau)
        roll = _sines(self.roll_terms, tau)
        return rotation_from_ypr(yaw, pitch, roll)

    def pose(self, t) -> np.ndarray:
        """4x4 (or (...,4,4) for array t) float64 T_world_cam at time(s) t."""
        t_arr = np.asarray(t, dtype=np.float64)
        T = np.zeros(t_arr.shape + (4, 4))
        T[..., :3, :3] = self.rotation(t_arr)
        T[..., :3, 3] = self.position(t_arr)
        T[..., 3, 3] = 1.0
        return T

    # -- random construction -----------------------------------------------------------------------
    @classmethod
    def random(cls, rng: np.random.Generator, center: Tuple[float, float], max_ax: float, max_ay: float,
               height_range: Tuple[float, float], speed_range: Tuple[float, float],
               pitch_range_deg: Tuple[float, float], yaw_offset_deg: Tuple[float, float],
               yaw_sway_deg: float, roll_deg: float, shake_m: float, tremor_deg: float,
               loop_fill: Tuple[float, float] = (0.35, 0.85)) -> 'HandheldTrajectory':
        """A random loop that fits in ``[center +- max_ax] x [center +- max_ay]`` (before hand shake).

        ``height_range`` bounds the camera height of the loop; ``speed_range`` bounds the walking speed;
        the yaw offset from the walking direction has a mean drawn from ``yaw_offset_deg`` (towards the
        inside of the loop) and a slow sway of up to ``yaw_sway_deg``; ``roll_deg`` bounds the roll;
        ``shake_m`` bounds the hand shake (metres); ``tremor_deg`` the rotational tremor.
        """
        u = rng.uniform
        radial = [(2, u(0.0, 0.12), u(0, 2 * math.pi)), (3, u(0.0, 0.08), u(0, 2 * math.pi))]
        rmax = 1.0 + sum(a for _, a, _ in radial)
        fill_x, fill_y = u(*loop_fill), u(*loop_fill)
        ax = max(0.05, fill_x * max_ax / rmax)
        ay = max(0.05, fill_y * max_ay / rmax)
        h_lo, h_hi = height_range
        hb1 = u(0.0, 0.25) * (h_hi - h_lo) / 2
        hb2 = u(0.0, 0.25) * (h_hi - h_lo) / 2
        h0 = u(h_lo + hb1 + hb2, h_hi - hb1 - hb2)
        heights = [(1, hb1, u(0, 2 * math.pi)), (2, hb2, u(0, 2 * math.pi))]
        v_lo, v_hi = speed_range
        v_mean = u(v_lo + 0.25 * (v_hi - v_lo), v_hi - 0.25 * (v_hi - v_lo))
        v_amp = min(v_mean - v_lo, v_hi - v_mean)
        a1 = u(0.3, 0.6) * v_amp
        a2 = u(0.0, 1.0) * (v_amp - a1)
        speeds = [(a1, u(0.2, 0.8), u(0, 2 * math.pi)), (a2, u(0.8, 2.0), u(0, 2 * math.pi))]
        direction = 1 if rng.random() < 0.5 else -1
        deg = math.pi / 180
        yaw_mean = direction * u(*yaw_offset_deg) * deg
        s1 = u(0.4, 0.7) * yaw_sway_deg * deg
        s2 = u(0.0, 1.0) * (yaw_sway_deg * deg - s1)
        yaw_terms = [(s1, u(0.15, 0.45), u(0, 2 * math.pi)), (s2, u(0.5, 1.1), u(0, 2 * math.pi))]
        p_lo, p_hi = pitch_range_deg
        p_amp = u(0.3, 0.5) * (p_hi - p_lo)
        pitch_mean = u(p_lo + p_amp / 2, p_hi - p_amp / 2) * deg
        pa = u(0.4, 0.7) * p_amp / 2
        pitch_terms = [(pa * deg, u(0.2, 0.6), u(0, 2 * math.pi)),
                       ((p_amp / 2 - pa) * deg, u(0.6, 1.4), u(0, 2 * math.pi))]
        r1 = u(0.3, 0.7) * roll_deg
        roll_terms = [(r1 * deg, u(0.2, 0.7), u(0, 2 * math.pi)),
                      ((roll_deg - r1) * u(0, 1) * deg, u(0.7, 1.6), u(0, 2 * math.pi))]
        # rotational tremor (hand), a few Hz, small
        for terms in (yaw_terms, pitch_terms, roll_terms):
            terms.append((u(0.3, 1.0) * tremor_deg * deg, 2 * math.pi * u(1.0, 3.0), u(0, 2 * math.pi)))
        # positional hand shake: walking bob (vertical, ~1.5-2 Hz) plus small lateral sway
        bob = u(0.3, 0.6) * shake_m
        sway = shake_m - bob
        sway_dir = rng.normal(size=3)
        sway_dir = sway_dir / max(np.linalg.norm(sway_dir), 1e-9)
        shake = [((0.0, 0.0, bob), 2 * math.pi * u(1.4, 2.0), (0.0, 0.0, u(0, 2 * math.pi))),
                 (tuple(float(v) for v in sway_dir * sway), 2 * math.pi * u(0.6, 1.2),
                  tuple(float(v) for v in u(0, 2 * math.pi, 3)))]
        return cls(center=(float(center[0]), float(center[1])), ax=float(ax), ay=float(ay), radial_terms=radial,
                   height0=float(h0), height_terms=heights, direction=direction, speed_mean=float(v_mean),
                   speed_terms=speeds, t0=float(u(0, 1000.0)), shake_terms=shake, yaw_offset_mean=yaw_mean,
                   yaw_terms=yaw_terms, pitch_mean=pitch_mean, pitch_terms=pitch_terms, roll_terms=roll_terms)


def corruption_variance(T_world_cam: Sequence[np.ndarray], trans_noise_rel: float = 0.03,
                        rot_noise_deg: float = 0.5) -> np.ndarray:
    """The accumulated pose variance that an honest odometry would publish for :func:`corrupt_trajectory`'s noise
    (same ``trans_noise_rel`` and ``rot_noise_deg``), one row per pose: (position variance per axis in m^2, rotation
    variance per axis in rad^2: the means of the diagonal of the pose covariance), zero at the first pose.

    First-order propagation of the world-frame error (dp, dtheta) along the trajectory: a step w (world frame) from a
    pose whose rotation is off by dtheta lands off by dtheta x w, so dp' = dp - [w]x dtheta + e_t and
    dtheta' = dtheta + e_r, with e_t of length ``trans_noise_rel * |w|`` and e_r of ``rot_noise_deg`` in random
    directions (per-axis variances a third of their squares): P' = F P F^T + Q with F = [[I, -[w]x], [0, I]]. The
    cross-covariance between position and heading is carried, so the position variance grows with the cube of the
    path where the heading error dominates, as the noise does.
    """
    T_world_cam = [np.asarray(T, dtype=np.float64) for T in T_world_cam]
    q_rot = math.radians(rot_noise_deg) ** 2 / 3.0
    P_66 = np.zeros((6, 6), np.float64)
    var_n2 = np.zeros((len(T_world_cam), 2), np.float64)
    for i in range(1, len(T_world_cam)):
        w = T_world_cam[i][:3, 3] - T_world_cam[i - 1][:3, 3]
        F_66 = np.eye(6)
        F_66[:3, 3:] = -np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
        Q_66 = np.diag([(trans_noise_rel * float(np.linalg.norm(w))) ** 2 / 3.0] * 3 + [q_rot] * 3)
        P_66 = F_66 @ P_66 @ F_66.T + Q_66
        var_n2[i] = [np.trace(P_66[:3, :3]) / 3.0, np.trace(P_66[3:, 3:]) / 3.0]
    return var_n2


def corruption_twist_variance(T_world_cam: Sequence[np.ndarray], stamps: Sequence[float],
                              trans_noise_rel: float = 0.03, rot_noise_deg: float = 0.5) -> np.ndarray:
    """The twist variance that an honest wheel odometry would publish for :func:`corrupt_trajectory`'s noise, one row
    per pose: (linear variance per axis in m^2/s, angular variance per axis in rad^2/s), the rates that
    ``twist.covariance`` is read as (``dpv_sensor.core.odometry_covariance``).

    The noise model adds to the step from pose i-1 to pose i (``dt_i`` seconds, ``s_i`` metres) a translation error of
    length ``trans_noise_rel * s_i`` and a rotation error of ``rot_noise_deg`` in random directions: per-axis
    variances ``(trans_noise_rel s_i)^2 / 3`` and ``radians(rot_noise_deg)^2 / 3`` gained over ``dt_i``, i.e. rates
    of those divided by ``dt_i`` (row i; row 0 repeats row 1). Integrated over an interval they give back the noise
    model's variance of the relative motion (the rotation's lever on the path after it comes with the integration).
    """
    T_world_cam = [np.asarray(T, dtype=np.float64) for T in T_world_cam]
    t = np.asarray(stamps, dtype=np.float64)
    if len(T_world_cam) < 2 or t.shape != (len(T_world_cam),) or np.any(np.diff(t) <= 0):
        raise ValueError('corruption_twist_variance needs two or more poses with increasing stamps, one per pose')
    q_rot = math.radians(rot_noise_deg) ** 2 / 3.0
    out = np.zeros((len(T_world_cam), 2), np.float64)
    for i in range(1, len(T_world_cam)):
        dt = t[i] - t[i - 1]
        step = float(np.linalg.norm(T_world_cam[i][:3, 3] - T_world_cam[i - 1][:3, 3]))
        out[i] = [(trans_noise_rel * step) ** 2 / 3.0 / dt, q_rot / dt]
    out[0] = out[1]
    return out


def corrupt_trajectory(T_world_cam: Sequence[np.ndarray], trans_noise_rel: float = 0.03,
                       rot_noise_deg: float = 0.5, scale_bias: float = 0.0, seed: int = 0) -> List[np.ndarray]:
    """Odometry-like corruption of a trajectory (pose-refinement experiments, training augmentation, tests).

    Every relative motion between consecutive poses gets a translation error of ``trans_noise_rel`` times its
    length in a random direction (drift that accumulates as a random walk), a scale error ``scale_bias``
    (systematic; monocular photometry cannot observe it), and a rotation error of ``rot_noise_deg`` degrees about
    a random axis. The corrupted motions are chained from the first pose (which stays exact).
    """
    rng = np.random.default_rng(seed)
    T_world_cam = [np.asarray(T, dtype=np.float64) for T in T_world_cam]
    out = [T_world_cam[0].copy()]
    for i in range(1, len(T_world_cam)):
        rel = np.linalg.inv(T_world_cam[i - 1]) @ T_world_cam[i]
        step = float(np.linalg.norm(rel[:3, 3]))
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        noisy = rel.copy()
        noisy[:3, 3] = rel[:3, 3] * (1.0 + scale_bias) + trans_noise_rel * step * d
        noisy[:3, :3] = Rotation.from_rotvec(axis * math.radians(rot_noise_deg)).as_matrix() @ rel[:3, :3]
        out.append(out[-1] @ noisy)
    return out
