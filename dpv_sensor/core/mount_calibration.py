"""The camera mount and the camera-odometry time offset, measured by the images (hand-eye calibration).

The node composes each image's odometry pose with a mount ``M`` (``T_base_camera``) and pairs the image stamped
``t`` with the odometry at ``t``. A real robot's mount is often a few degrees and centimetres off (a URDF from a
drawing, a tracker clipped beside the camera) and its odometry is stamped tens of milliseconds off. Model:

    T_world_cam_true(t) = T_used(t + dt) F,    F = (E, p)

``T_used(t)``: the camera pose the node uses (the odometry at ``t`` composed with ``M``); ``F``: the true camera's
pose in the camera frame the node assumes, rotation ``E`` and translation ``p`` (the real mount is ``M F``);
``dt``: the image stamped ``t`` was taken when the odometry's clock said ``t + dt`` (``dt > 0``: the odometry is
stamped late; look it up ``dt`` later).

A pair of images (a, b) then moved by ``P = F^-1 Q F`` with ``Q = T_used(t_b + dt)^-1 T_used(t_a + dt)``, and every
match of the pair must lie on the epipolar line of ``P``: the Sampson distance of ``x_b^T [t_P]x R_P x_a``
(pixels), where the pair translated; the distance of ``x_b`` from ``R_P x_a`` where it barely did (a turn in place:
the matches then say the rotation alone). The matches are scored against the model itself, not through an estimate
of each pair's motion: the pairs of a keyframe window are a few centimetres apart, where a pair's own direction is
unknown to tens of degrees and its rotation to half a degree, while the odometry's metric motion fixes both. ``E``
turns the odometry's translation direction by its own angle (observed by every pair that moved sideways to it)
and a pair's rotation axis (by about the angle it turned); ``p`` changes the translation by ``(R_Q - I) p`` (observed
where the camera turned while moving); ``dt`` shows where the motion changes between ``t_a`` and ``t_b``.

:func:`fit_mount` minimises the robust (Cauchy) sum of the distances over every pair's matches: ``dt`` on a grid
with the rotation alone first, then Gauss-Newton on ``(E, p, dt)``. The matches of a pair share errors (a flow
field, lens distortion, rolling shutter), so the covariance is the sandwich over pairs, ``H^-1 (sum_i g_i g_i^T)
H^-1`` with ``g_i`` the gradient of pair i: it is as wide as the pairs disagree, not as narrow as thousands of
matches would make it. :class:`PoseTrack` interpolates the poses the node used (SLERP and linear between samples).
No ROS, no torch.
"""
from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, field
from typing import List, Optional, Sequence, Tuple

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = ['PairMatchSet', 'normalised_matches', 'PoseTrack', 'MountFit', 'MountFitConfig', 'fit_mount',
           'corrected_mount']


@dataclass
class PairMatchSet:
    """One pair's matches: ``xa_n3`` in the image stamped ``t_a`` and ``xb_n3`` in the one stamped ``t_b`` (seconds),
    as normalised homogeneous image coordinates (``K^-1 [u, v, 1]``), ``focal_px`` the focal length in pixels they
    were measured at (distances are scored in its pixels)."""
    t_a: float
    t_b: float
    xa_n3: np.ndarray
    xb_n3: np.ndarray
    focal_px: float


def normalised_matches(t_a: float, t_b: float, pa_n2: np.ndarray, pb_n2: np.ndarray, K_33: np.ndarray,
                       max_points: int) -> PairMatchSet:
    """A :class:`PairMatchSet` from pixel matches (at most ``max_points``, evenly spaced through the list)."""
    n = len(pa_n2)
    idx = np.unique(np.linspace(0, n - 1, min(n, max_points)).round().astype(int)) if n else np.zeros(0, int)
    Kinv = np.linalg.inv(np.asarray(K_33, np.float64))
    xa = np.c_[np.asarray(pa_n2, np.float64)[idx], np.ones(len(idx))] @ Kinv.T
    xb = np.c_[np.asarray(pb_n2, np.float64)[idx], np.ones(len(idx))] @ Kinv.T
    K = np.asarray(K_33, np.float64)
    return PairMatchSet(float(t_a), float(t_b), xa, xb, 0.5 * float(K[0, 0] + K[1, 1]))


class PoseTrack:
    """The camera poses the node used, by stamp (seconds, increasing): rotations interpolated by SLERP, positions
    linearly between the two samples around a time; nothing outside the samples or across a gap longer than
    ``max_gap_s``."""

    def __init__(self, max_gap_s: float = 0.5):
        self.max_gap_s = float(max_gap_s)
        self._t: List[float] = []
        self._T: List[np.ndarray] = []

    def __len__(self) -> int:
        return len(self._t)

    def add(self, stamp_s: float, T_world_cam_44: np.ndarray) -> None:
        """A sample; one not after the last is ignored (stamps only increase)."""
        if self._t and stamp_s <= self._t[-1]:
            return
        self._t.append(float(stamp_s))
        self._T.append(np.asarray(T_world_cam_44, np.float64)[:4, :4].copy())

    def forget_before(self, stamp_s: float) -> None:
        """Drop the samples older than ``stamp_s`` (keeps one before it, for interpolation)."""
        i = max(0, bisect.bisect_left(self._t, stamp_s) - 1)
        if i:
            del self._t[:i]
            del self._T[:i]

    def clear(self) -> None:
        self._t.clear()
        self._T.clear()

    @property
    def span(self) -> Tuple[float, float]:
        return (self._t[0], self._t[-1]) if self._t else (math.inf, -math.inf)

    def poses_at(self, stamps_s: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(n, 3, 3) rotations, (n, 3) positions at ``stamps_s`` and an (n,) mask of the stamps that have them."""
        t = np.asarray(stamps_s, np.float64).ravel()
        if len(self._t) < 2:
            return np.tile(np.eye(3), (len(t), 1, 1)), np.zeros((len(t), 3)), np.zeros(len(t), bool)
        ts = np.asarray(self._t)
        j = np.searchsorted(ts, t, side='right')
        inside = ((j > 0) & (j < len(ts))) | (t == ts[-1])
        j = np.clip(j, 1, len(ts) - 1)
        gap = ts[j] - ts[j - 1]
        on_sample = (t == ts[j - 1]) | (t == ts[j])
        ok = inside & ((gap <= self.max_gap_s) | on_sample)
        Ts = np.asarray(self._T)
        T0, T1 = Ts[j - 1], Ts[j]
        alpha = np.clip((t - ts[j - 1]) / np.maximum(gap, 1e-12), 0.0, 1.0)
        step = Rotation.from_matrix(np.einsum('nji,njk->nik', T0[:, :3, :3], T1[:, :3, :3])).as_rotvec()
        R = T0[:, :3, :3] @ Rotation.from_rotvec(alpha[:, None] * step).as_matrix()
        c = T0[:, :3, 3] + alpha[:, None] * (T1[:, :3, 3] - T0[:, :3, 3])
        return R, c, ok


@dataclass
class MountFitConfig:
    """max_offset_s: the time offsets searched (+-, seconds; 0: the offset is not fitted, held at 0);
    grid_step_s: the grid's step; scale_px: the Cauchy loss's scale (pixels: a match this far off weighs half);
    min_pairs: fewer usable pairs is no estimate; min_baseline_m: a pair whose odometry moved less than this is
    scored as a turn in place (the rotation alone); min_matches: a pair with fewer matches is left out;
    fit_translation: also fit the mount's translation (when at least min_pairs pairs turned 2 deg or more while
    moving); iterations: Gauss-Newton steps."""
    max_offset_s: float = 0.1
    grid_step_s: float = 0.01
    scale_px: float = 1.0
    min_pairs: int = 8
    min_baseline_m: float = 0.005
    min_matches: int = 20
    fit_translation: bool = True
    iterations: int = 8
    floor_rot_deg: float = 0.1
    floor_trans_m: float = 0.01
    floor_time_s: float = 0.001


@dataclass
class MountFit:
    """ok: an estimate exists (reason says why not); rotvec_rad: ``E`` as a rotation vector (camera axes) and
    cov_rot_33 its covariance (rad^2); translation_m: ``p`` (m, camera axes; zeros when not fitted) and cov_trans_33
    (inf when not fitted); time_offset_s / sigma_time_s: ``dt`` and its std (0 / inf when not fitted); pairs and
    matches used; median_px: the matches' median distance at the solution. The covariances include the floors of
    :class:`MountFitConfig` (what the estimate erred by on renders with exact poses)."""
    ok: bool
    reason: Optional[str] = None
    rotvec_rad: np.ndarray = field(default_factory=lambda: np.zeros(3))
    cov_rot_33: np.ndarray = field(default_factory=lambda: np.diag(np.full(3, math.inf)))
    time_offset_s: float = 0.0
    sigma_time_s: float = math.inf
    pairs: int = 0
    matches: int = 0
    median_px: float = 0.0
    translation_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    cov_trans_33: np.ndarray = field(default_factory=lambda: np.full((3, 3), math.inf))

    @property
    def sigma_trans_m(self) -> np.ndarray:
        """The std (m) of each axis of ``translation_m`` (inf where it was not fitted)."""
        return np.sqrt(np.maximum(np.diag(self.cov_trans_33), 0.0))

    @property
    def angle_deg(self) -> float:
        return math.degrees(float(np.linalg.norm(self.rotvec_rad)))

    @property
    def sigma_rot_deg(self) -> np.ndarray:
        """The std (deg) of each axis of ``rotvec_rad`` (camera x, y, z)."""
        return np.degrees(np.sqrt(np.maximum(np.diag(self.cov_rot_33), 0.0)))

    @property
    def worst_sigma_deg(self) -> float:
        """The std (deg) of the least observed direction of the rotation."""
        return math.degrees(math.sqrt(max(float(np.linalg.eigvalsh(self.cov_rot_33)[-1]), 0.0)))

    def rotation_significance(self) -> float:
        """How many sigmas the rotation is from none: sqrt(rotvec^T cov^-1 rotvec) over the observed directions
        (a direction with a std above 10 deg counts as unobserved)."""
        w, V = np.linalg.eigh(self.cov_rot_33)
        seen = w < math.radians(10.0) ** 2
        if not np.any(seen):
            return 0.0
        z = V[:, seen].T @ self.rotvec_rad
        return float(math.sqrt(float(np.sum(z ** 2 / w[seen]))))


def _skew_n(v_n3: np.ndarray) -> np.ndarray:
    z = np.zeros(len(v_n3))
    return np.stack([np.stack([z, -v_n3[:, 2], v_n3[:, 1]], -1), np.stack([v_n3[:, 2], z, -v_n3[:, 0]], -1),
                     np.stack([-v_n3[:, 1], v_n3[:, 0], z], -1)], 1)


class _Problem:
    """Every pair's matches, concatenated, and the node's relative poses at any time offset."""

    def __init__(self, pairs: Sequence[PairMatchSet], track: PoseTrack):
        self.ta = np.array([p.t_a for p in pairs], np.float64)
        self.tb = np.array([p.t_b for p in pairs], np.float64)
        self.pair = np.concatenate([np.full(len(p.xa_n3), i) for i, p in enumerate(pairs)])
        self.xa = np.concatenate([p.xa_n3 for p in pairs])
        self.xb = np.concatenate([p.xb_n3 for p in pairs])
        self.f = np.concatenate([np.full(len(p.xa_n3), p.focal_px) for p in pairs])
        self.n_pairs = len(pairs)
        self.track = track

    def motion(self, dt: float) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(R_Q (n, 3, 3), t_Q (n, 3), where both ends exist) of Q = T(t_b + dt)^-1 T(t_a + dt)."""
        Ra, ca, oka = self.track.poses_at(self.ta + dt)
        Rb, cb, okb = self.track.poses_at(self.tb + dt)
        RQ = np.einsum('nji,njk->nik', Rb, Ra)
        tQ = np.einsum('nji,nj->ni', Rb, ca - cb)
        return RQ, tQ, oka & okb

    def distances(self, x7: np.ndarray, motion, moved: np.ndarray) -> np.ndarray:
        """Each match's distance (pixels) under x = (phi, p, dt) and the odometry's motion at dt: the Sampson
        distance to P's epipolar geometry for pairs that ``moved``, else x_b's distance from R_P x_a (the x and y
        of the normalised difference, as two residuals; the Sampson one has a zero second)."""
        RQ, tQ = motion[0], motion[1]
        E = Rotation.from_rotvec(x7[:3]).as_matrix()
        p = x7[3:6]
        RP = np.einsum('ji,njk,kl->nil', E, RQ, E)
        tP = (RQ @ p + tQ - p) @ E                      # rows: E^T (R_Q p + t_Q - p)
        tP = tP / np.maximum(np.linalg.norm(tP, axis=1, keepdims=True), 1e-12)
        i = self.pair
        Rx = np.einsum('nij,nj->ni', RP[i], self.xa)
        Ex = np.cross(tP[i], Rx)                         # E x_a with E = [t]x R
        Etx = np.einsum('nji,nj->ni', _skew_n(tP[i]) @ RP[i], self.xb)
        num = np.sum(self.xb * Ex, axis=1)
        den = np.sqrt(np.maximum(Ex[:, 0] ** 2 + Ex[:, 1] ** 2 + Etx[:, 0] ** 2 + Etx[:, 1] ** 2, 1e-18))
        sampson = np.c_[self.f * num / den, np.zeros(len(num))]
        proj = Rx[:, :2] / Rx[:, 2:3] - self.xb[:, :2] / self.xb[:, 2:3]
        turned = self.f[:, None] * proj
        return np.where(moved[i][:, None], sampson, turned)


def _robust_cost(r_n2: np.ndarray, scale: float) -> float:
    """The Cauchy loss summed over the matches."""
    return float(np.sum(np.log1p(np.sum(r_n2 ** 2, axis=1) / scale ** 2)))


def _cauchy_weights(r_n2: np.ndarray, scale: float) -> np.ndarray:
    return 1.0 / (1.0 + np.sum(r_n2 ** 2, axis=1) / scale ** 2)


#: the numerical Jacobian's steps: rotation (rad), translation (m), time (s)
_STEPS = np.r_[np.full(3, 1e-6), np.full(3, 1e-5), 1e-3]


def _gauss_newton(prob: _Problem, x7: np.ndarray, free: np.ndarray, moved: np.ndarray, cfg: MountFitConfig,
                  iterations: int):
    """(x, H, the pairs' gradient outer-product sum, robust cost) after IRLS Gauss-Newton steps from x7 =
    (phi, p, dt), moving only the parameters where ``free`` is True."""
    x = np.asarray(x7, np.float64).copy()
    idx = np.flatnonzero(free)
    motions = {}

    def residuals(x_):
        t = float(x_[6])
        if t not in motions:
            motions[t] = prob.motion(t)
        return prob.distances(x_, motions[t], moved)

    for it in range(iterations + 1):
        r = residuals(x)
        w = _cauchy_weights(r, cfg.scale_px)
        J = np.empty((r.size, len(idx)))
        for col, j in enumerate(idx):
            d = np.zeros(7)
            d[j] = _STEPS[j]
            J[:, col] = (residuals(x + d) - residuals(x - d)).ravel() / (2.0 * _STEPS[j])
        ww = np.repeat(w, 2)
        H = J.T @ (J * ww[:, None])
        grad_rows = J * (ww * r.ravel())[:, None]
        if it == iterations:
            break
        step = np.linalg.lstsq(H + np.eye(len(idx)) * 1e-9 * max(1.0, float(np.trace(H))),
                               -grad_rows.sum(0), rcond=None)[0]
        full = np.zeros(7)
        full[idx] = step
        full[6] = float(np.clip(full[6], -cfg.grid_step_s, cfg.grid_step_s))
        full[3:6] = np.clip(full[3:6], -0.05, 0.05)
        x = x + full
    per_pair = np.zeros((prob.n_pairs, len(idx)))
    np.add.at(per_pair, np.repeat(prob.pair, 2), grad_rows)
    return x, H, per_pair.T @ per_pair, _robust_cost(r, cfg.scale_px)


def fit_mount(pairs: Sequence[PairMatchSet], track: PoseTrack, config: Optional[MountFitConfig] = None) -> MountFit:
    """The mount rotation ``E``, translation ``p`` and time offset ``dt`` that best explain the pairs' matches with
    the track's motion (module doc). Pairs with fewer than ``min_matches`` matches, or whose ends (shifted by any
    searched offset) the track does not cover, are left out."""
    cfg = config or MountFitConfig()
    fit_time = cfg.max_offset_s > 0
    pairs = [p for p in pairs if len(p.xa_n3) >= cfg.min_matches]
    prob = _Problem(pairs, track) if pairs else None
    inside = np.ones(len(pairs), bool)
    for shift in (-cfg.max_offset_s, 0.0, cfg.max_offset_s):
        if prob is not None:
            inside &= prob.motion(shift)[2]
    pairs = [p for p, ok in zip(pairs, inside) if ok]
    if len(pairs) < cfg.min_pairs:
        return MountFit(False, f'too few image pairs inside the odometry ({len(pairs)} < {cfg.min_pairs})',
                        pairs=len(pairs))
    prob = _Problem(pairs, track)
    RQ, tQ, _ = prob.motion(0.0)
    moved = np.linalg.norm(tQ, axis=1) >= cfg.min_baseline_m
    turned = Rotation.from_matrix(RQ).magnitude() >= math.radians(2.0)
    fit_trans = cfg.fit_translation and int(np.sum(moved & turned)) >= cfg.min_pairs
    free = np.r_[np.ones(3, bool), np.full(3, fit_trans), fit_time]
    x = np.zeros(7)
    if fit_time:
        # the offset's start: the grid point whose robust cost is least with the mount in use (the offset shows
        # where the motion changes, which a mount error of a few degrees hardly moves)
        grid = np.arange(-cfg.max_offset_s, cfg.max_offset_s + 0.5 * cfg.grid_step_s, cfg.grid_step_s)
        costs = [_robust_cost(prob.distances(np.r_[np.zeros(6), g], prob.motion(float(g)), moved), cfg.scale_px)
                 for g in grid]
        x[6] = float(grid[int(np.argmin(costs))])
    x, H, S, _ = _gauss_newton(prob, x, free, moved, cfg, cfg.iterations)
    n = len(pairs)
    k = int(np.sum(free))
    Hinv = np.linalg.pinv(H)
    cov_free = Hinv @ S @ Hinv * (n / max(n - k, 1))
    cov = np.full((7, 7), math.inf)
    cov[np.ix_(free, free)] = cov_free
    floors = np.r_[np.full(3, math.radians(cfg.floor_rot_deg)), np.full(3, cfg.floor_trans_m), cfg.floor_time_s]
    cov[np.diag_indices(7)] += floors ** 2
    dist = np.linalg.norm(prob.distances(x, prob.motion(float(x[6])), moved), axis=1)
    return MountFit(True, None, x[:3].copy(), cov[:3, :3].copy(), float(x[6]) if fit_time else 0.0,
                    math.sqrt(max(float(cov[6, 6]), 0.0)) if fit_time else math.inf, n, len(dist),
                    float(np.median(dist)), x[3:6].copy() if fit_trans else np.zeros(3), cov[3:6, 3:6].copy())


def corrected_mount(T_base_camera_44: np.ndarray, fit: MountFit) -> np.ndarray:
    """The mount the fit says is right: ``M F`` with ``F`` the fit's rotation and translation (the translation
    only where it was fitted)."""
    F = np.eye(4)
    F[:3, :3] = Rotation.from_rotvec(np.asarray(fit.rotvec_rad, np.float64)).as_matrix()
    if np.all(np.isfinite(fit.cov_trans_33)):
        F[:3, 3] = fit.translation_m
    return np.asarray(T_base_camera_44, np.float64) @ F
