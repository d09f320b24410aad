"""The Bayesian DPV filter (paper Sec. 3.2, eqs. 5-10), in energy space E = -log p.

Per frame, :meth:`DPVFilter.step`

1. decides whether to *reset* (first frame, volume layout changed, non-finite pose, time going
   backwards, a time gap above ``max_time_gap``, a pose *jump*); a reset returns the measurement alone
   and restarts from it. A jump is judged against the time elapsed since the previous step (see
   :func:`jump_limit`): more than ``max_translation`` metres / ``max_rotation_deg`` degrees per second,
   and never less than those values (an interval shorter than ``MOTION_REFERENCE_S`` = 1 s is held to
   them). So steps that are far apart in time - keyframes of a stream whose frames were dropped in
   between - do not reset while the camera moved continuously; a large real motion is handled by the
   prediction itself (voxels outside the old frustum get the uniform prior). Only a motion faster than
   the camera can move (an odometry teleport) restarts the belief.
2. otherwise *predicts* the previous belief into the new camera with
   :func:`dpv_sensor.core.geometry.warp_volume` (eq. 5; voxels the old camera never saw get the uniform
   prior) and
3. *updates* it with the measurement, by mode:

   - ``none``:   E = E_meas                                  (no filtering)
   - ``bayes``:  E = E_pred + E_meas                         (eq. 6 / 7)
   - ``global``: E = lambda * E_pred + E_meas                (eq. 8, ``damping`` = lambda)
   - ``knet``:   E = E_pred + g(E_meas - E_pred, image)      (eqs. 9-10, ``knet`` = g)

Every volume is renormalised after every step and its log-probabilities are clamped at
``log_floor`` (default -30, then renormalised), so energies stay in [0, ~30]: a voxel the
prediction considers impossible can still be won back by a few consistent measurements instead of
being locked at -inf forever, and no NaN/inf can enter the state.

The filter is batched: B independent streams that share stamps (pose-based resets act per batch
element). It holds no ROS types and works on CPU and CUDA alike.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, List, Optional

import torch

from dpv_sensor import params as _params
from dpv_sensor.core.dpv import LOG_FLOOR, clamp_log, rescale_depth
from dpv_sensor.core.geometry import invert_se3, rotation_angle, warp_volume

__all__ = ['DPVFilter', 'FilterStep', 'MODES', 'MOTION_REFERENCE_S', 'jump_limit']

MODES = ('none', 'bayes', 'global', 'knet')

# The pose-jump thresholds are motions per this many seconds, and apply unscaled below it.
MOTION_REFERENCE_S = 1.0


def jump_limit(limit: float, elapsed_s: float) -> float:
    """Largest camera motion (metres or degrees) accepted as continuous over ``elapsed_s`` seconds.

    ``limit`` is the motion allowed per ``MOTION_REFERENCE_S`` (1 s): the bound grows linearly with the
    elapsed time (a speed limit), but is never below ``limit`` itself, so consecutive frames of a
    stream (milliseconds apart) are held to ``limit`` exactly as an absolute jump threshold. A motion
    above the bound is physically implausible for a camera and treated as a teleport (odometry reset,
    relocalisation). ``limit = inf`` disables the rule.
    """
    return float(limit) * max(1.0, float(elapsed_s) / MOTION_REFERENCE_S)


@dataclass
class FilterStep:
    """Result of one :meth:`DPVFilter.step`.

    logp_bdhw: the posterior (filtered) DPV, log-probabilities.
    predicted_logp_bdhw: the prediction from the previous belief (eq. 5), or None when there was
        none (reset, or mode 'none').
    reset_reason: why the filter (re)started at this step, or None when it did not. When only some
        batch elements reset, the reason names them ("... in batch elements [1]").
    """
    logp_bdhw: torch.Tensor
    predicted_logp_bdhw: Optional[torch.Tensor]
    reset_reason: Optional[str]


class DPVFilter:
    """Bayesian filter over depth probability volumes (see the module docstring).

    Args:
        mode: 'none' | 'bayes' | 'global' | 'knet'.
        damping: lambda of global damping (eq. 8), in [0, 1]; only used by mode 'global'.
        knet: callable ``g(residual_bdhw, image_b3hw) -> correction_bdhw`` (mode 'knet'), where
            residual = E_meas - E_pred (eq. 10); image may be None if the caller gave none.
        max_time_gap: seconds; a larger gap between consecutive steps resets the filter. It judges
            the time between *steps*: a caller that steps on a subset of a stream (keyframes, frames
            left out while busy) should pass ``math.inf`` and check the stream's own continuity itself
            (the Estimator does, with ``Frame.sensor_gap_s``).
        max_translation: metres per second of elapsed time between consecutive steps, at least
            ``max_translation`` metres (:func:`jump_limit`); a faster camera motion resets.
        max_rotation_deg: degrees per second, likewise, for the camera rotation.
        log_floor: lowest log-probability kept (energies are capped at -log_floor).
    """

    def __init__(self, mode: str = 'global', damping: float = _params.default('damping'),
                 knet: Optional[Callable[[torch.Tensor, Optional[torch.Tensor]], torch.Tensor]] = None,
                 max_time_gap: float = 1.0, max_translation: float = 1.0, max_rotation_deg: float = 30.,
                 log_floor: float = LOG_FLOOR):
        if mode not in MODES:
            raise ValueError(f'mode must be one of {MODES}, got {mode!r}')
        if not 0.0 <= float(damping) <= 1.0:
            raise ValueError(f'damping must be in [0, 1], got {damping}')
        if mode == 'knet' and knet is None:
            raise ValueError("mode 'knet' needs a knet callable g(residual, image) -> correction")
        if max_time_gap <= 0 or max_translation <= 0 or max_rotation_deg <= 0:
            raise ValueError('max_time_gap, max_translation and max_rotation_deg must be positive')
        if not log_floor < 0:
            raise ValueError(f'log_floor must be negative, got {log_floor}')
        self.mode = mode
        self.damping = float(damping)
        self.knet = knet
        self.max_time_gap = float(max_time_gap)
        self.max_translation = float(max_translation)
        self.max_rotation_deg = float(max_rotation_deg)
        self.log_floor = float(log_floor)
        self.reset()

    # ------------------------------------------------------------------ state

    def reset(self) -> None:
        """Forget the belief; the next step starts from its measurement ('first frame')."""
        self._logp: Optional[torch.Tensor] = None
        self._K: Optional[torch.Tensor] = None
        self._T_world_cam: Optional[torch.Tensor] = None
        self._pose_ok: Optional[torch.Tensor] = None
        self._stamp: Optional[float] = None
        self._depths: Optional[torch.Tensor] = None

    @property
    def logp_bdhw(self) -> Optional[torch.Tensor]:
        """Current belief (log-probabilities) or None before the first step."""
        return self._logp

    @property
    def T_world_cam_b44(self) -> Optional[torch.Tensor]:
        """Camera pose of the current belief, or None."""
        return self._T_world_cam

    @property
    def K_b33(self) -> Optional[torch.Tensor]:
        """Intrinsics of the current belief's grid, or None."""
        return self._K

    @property
    def stamp(self) -> Optional[float]:
        """Time stamp (s) of the current belief, or None."""
        return self._stamp

    def predict(self, T_world_cam_b44: torch.Tensor, stride: int = 1) -> Optional[torch.Tensor]:
        """The current belief warped into another camera (eq. 5) without changing the state.

        Returns None when there is no belief or its pose is unknown. Used e.g. to get a depth and
        confidence for a new frame before its own measurement exists (pose refinement). ``stride``: only
        every ``stride``-th pixel of each axis (``geometry.warp_volume``), for a caller that needs a statistic.
        """
        if self._logp is None or self._T_world_cam is None or not bool(self._pose_ok.all()):
            return None
        T_b_a = invert_se3(T_world_cam_b44.to(self._logp)) @ self._T_world_cam
        pred = warp_volume(self._logp, self._K, T_b_a, self._depths, stride=stride)
        return clamp_log(pred, self.log_floor)

    def rescale_belief(self, log_scale_bhw: torch.Tensor) -> None:
        """Multiply the belief's depth by ``exp(log_scale)`` per pixel (:func:`~dpv_sensor.core.dpv.rescale_depth`,
        at the belief's own size): a correction of the newest keyframe that the next ones inherit. Nothing
        without a belief."""
        if self._logp is None:
            return
        d = self._depths
        self._logp = rescale_depth(self._logp, log_scale_bhw.to(self._logp), float(d[0]), float(d[-1]), self.log_floor)

    # ------------------------------------------------------------------ step

    def _sanitise(self, logp: torch.Tensor) -> torch.Tensor:
        logp = torch.nan_to_num(logp, nan=self.log_floor, posinf=0.0, neginf=self.log_floor)
        return clamp_log(torch.log_softmax(logp, dim=1), self.log_floor)

    def _reset_mask(self, meas, K, T, stamp, depths):
        """(global_reason or None, per-element reset mask (B,) bool, per-element reasons)."""
        B = meas.shape[0]
        finite = torch.isfinite(T.reshape(B, 16)).all(1)
        if self._logp is None:
            return 'first frame', None, []
        if (self._logp.shape != meas.shape or self._depths.shape != depths.shape
                or not torch.allclose(self._depths, depths) or not torch.allclose(self._K, K)):
            return 'volume layout changed (shape, planes or intrinsics)', None, []
        if stamp < self._stamp:
            return f'time went backwards ({stamp - self._stamp:+.3f} s)', None, []
        if stamp - self._stamp > self.max_time_gap:
            return f'time gap {stamp - self._stamp:.3f} s > max_time_gap {self.max_time_gap:.3f} s', None, []
        mask = ~finite | ~self._pose_ok
        reasons: List[str] = []
        if (~finite).any():
            reasons.append('non-finite pose')
        if (~self._pose_ok).any():
            reasons.append('previous pose was non-finite')
        ok = finite & self._pose_ok
        if ok.any():
            T_safe = torch.where(ok[:, None, None], T, torch.eye(4, dtype=T.dtype, device=T.device))
            prev = torch.where(ok[:, None, None], self._T_world_cam,
                               torch.eye(4, dtype=T.dtype, device=T.device))
            T_b_a = invert_se3(T_safe) @ prev
            trans = T_b_a[:, :3, 3].norm(dim=-1)
            rot = torch.rad2deg(rotation_angle(T_b_a[:, :3, :3]))
            elapsed = stamp - self._stamp
            lim_t = jump_limit(self.max_translation, elapsed)
            lim_r = jump_limit(self.max_rotation_deg, elapsed)
            jump_t = ok & (trans > lim_t)
            jump_r = ok & (rot > lim_r)
            if jump_t.any():
                reasons.append(f'pose jump: translation {trans[jump_t].max().item():.3f} m in {elapsed:.3f} s > '
                               f'{lim_t:.3f} m (max_translation {self.max_translation:.3f} m per second, '
                               'at least that)')
            if jump_r.any():
                reasons.append(f'pose jump: rotation {rot[jump_r].max().item():.1f} deg in {elapsed:.3f} s > '
                               f'{lim_r:.1f} deg (max_rotation_deg {self.max_rotation_deg:.1f} deg per second, '
                               'at least that)')
            mask = mask | jump_t | jump_r
        return None, mask, reasons

    def step(self, meas_logp_bdhw: torch.Tensor, K_b33: torch.Tensor, T_world_cam_b44: torch.Tensor,
             stamp: float, depths_d: torch.Tensor, image_b3hw: Optional[torch.Tensor] = None,
             update_weight_bhw: Optional[torch.Tensor] = None) -> FilterStep:
        """Fuse one measurement DPV taken by camera ``T_world_cam_b44`` at ``stamp`` (seconds).

        Args:
            meas_logp_bdhw: (B, D, H, W) measurement log-probabilities (e.g. D-Net or classical).
            K_b33: (B, 3, 3) intrinsics of the volume grid (H x W).
            T_world_cam_b44: (B, 4, 4) camera-to-world pose of this frame.
            stamp: time of this frame in seconds.
            depths_d: (D,) plane depths (uniform in inverse depth).
            image_b3hw: reference image for K-Net (passed through to ``knet``).
            update_weight_bhw: optional (B, H, W) weight in [0, 1] of this measurement per pixel (e.g. how
                much parallax the measurement had): the posterior is ``w * posterior + (1 - w) * base`` in
                log space, renormalised, where base is the prediction (or the uniform DPV where there is
                none: after a reset, outside the previous frustum). w = 0 leaves the belief exactly as
                predicted; w = 1 (or None) is the plain update.
        Returns:
            FilterStep(posterior logp, prediction or None, reset reason or None).
        """
        B = meas_logp_bdhw.shape[0]
        dt = meas_logp_bdhw.dtype
        dev = meas_logp_bdhw.device
        meas = self._sanitise(meas_logp_bdhw)
        K = K_b33.to(dtype=dt, device=dev).expand(B, 3, 3)
        T = T_world_cam_b44.to(dtype=dt, device=dev).expand(B, 4, 4)
        depths = torch.as_tensor(depths_d, dtype=dt, device=dev)
        stamp = float(stamp)

        global_reason, mask, reasons = self._reset_mask(meas, K, T, stamp, depths)
        finite = torch.isfinite(T.reshape(B, 16)).all(1)

        pred = None
        if global_reason is not None or bool(mask.all()):
            post = meas
            reason = global_reason if global_reason is not None else '; '.join(reasons)
        else:
            reason = None
            if self.mode == 'none':
                post = meas
            else:
                eye = torch.eye(4, dtype=dt, device=dev)
                T_safe = torch.where(mask[:, None, None], eye, T)
                prev = torch.where(mask[:, None, None], eye, self._T_world_cam)
                T_b_a = invert_se3(T_safe) @ prev
                pred = clamp_log(warp_volume(self._logp, K, T_b_a, depths), self.log_floor)
                post = self._update(pred, meas, image_b3hw)
            if mask.any():
                idx = mask.nonzero().flatten().tolist()
                post = torch.where(mask[:, None, None, None], meas, post)
                reason = f"{'; '.join(reasons)} in batch elements {idx}"

        if update_weight_bhw is not None:
            w = update_weight_bhw.to(dtype=dt, device=dev).clamp(0.0, 1.0)[:, None]
            base = torch.zeros_like(post) if pred is None else pred
            if pred is not None and mask is not None and mask.any():
                base = torch.where(mask[:, None, None, None], torch.zeros_like(post), base)
            post = clamp_log(w * post + (1.0 - w) * base, self.log_floor)

        self._logp = post.detach() if not torch.is_grad_enabled() else post
        self._K = K
        self._T_world_cam = torch.where(finite[:, None, None], T, torch.eye(4, dtype=dt, device=dev))
        self._pose_ok = finite
        self._stamp = stamp
        self._depths = depths
        return FilterStep(post, pred, reason)

    def _update(self, pred: torch.Tensor, meas: torch.Tensor, image: Optional[torch.Tensor]) -> torch.Tensor:
        E_pred, E_meas = -pred, -meas
        if self.mode == 'bayes':
            E = E_pred + E_meas
        elif self.mode == 'global':
            E = self.damping * E_pred + E_meas
        elif self.mode == 'knet':
            E = E_pred + self.knet(E_meas - E_pred, image)
        else:  # pragma: no cover - 'none' never predicts
            E = E_meas
        return clamp_log(-E, self.log_floor)
