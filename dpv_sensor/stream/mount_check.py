"""The mount check: the camera mount and the camera-odometry time offset, estimated live from the refinement
window's matches against the odometry the node used (stream layer, no ROS).

Nothing is matched twice: every pair of keyframes the window matched (its flow or its SIFT inliers,
``RefinementResult.matches``) joins the check once. A flow pair keeps the matches that the flow back from the
second image (a cheap DIS preset) returns to within ``ROUND_TRIP_PX``: the window's one-way flow errs
consistently near occlusions and in weak texture, which tilted the mount estimate by 0.4-0.5 deg on renders with
exact poses, 0.1 with the check. Every pushed frame's pose (the odometry composed with the mount in use) goes into
a pose track. As pairs come, :func:`dpv_sensor.core.mount_calibration.fit_mount` fits the mount's
rotation and translation and the time offset that best explain every pair's matches with the track's motion, each
with a sigma, on a thread of its own (the worker does not wait for it). Cost: the flow back, 5.6 ms a new pair
(one or two a keyframe); a fit, 0.3 s of a core on 20 pairs and 1 s on 91, the first at 8 pairs and each next
after twice as many new ones, at most every 128.

:class:`MountCheck` keeps the pairs (the newest ``max_pairs``) and the track, and reports a :class:`MountCheckStatus`:
the estimate, its sigma, and whether it is confidently away from the mount and the stamps in use
(``warn_sigmas`` sigmas and at least ``warn_rotation_deg`` / ``warn_translation_m`` / ``warn_offset_ms``): then
it logs one WARN naming the estimate (again only when the estimate has moved by that much since).
"""
from __future__ import annotations

import copy
import logging
import math
import threading
from dataclasses import dataclass, field
from typing import Any, Dict, Hashable, List, Optional, Set, Tuple

import numpy as np

from dpv_sensor.core.flow_rotation import FlowConfig, dense_flow, round_trip_px
from dpv_sensor.core.mount_calibration import (MountFit, MountFitConfig, PairMatchSet, PoseTrack, fit_mount,
                                               normalised_matches)

__all__ = ['MountCheckConfig', 'MountCheckStatus', 'MountCheck', 'pair_matches', 'fit_dict', 'mount_text',
           'offset_text', 'sequence_pairs']

LOG = logging.getLogger(__name__)

#: the matches of a pair the fit scores at most (evenly spaced through the pair's list)
MAX_PAIR_POINTS = 100
#: a flow match is kept when the flow back from the second image returns within this (pixels)
ROUND_TRIP_PX = 0.5
#: the flow back: DIS's fast preset (5 ms on a 640x480 pair here, against 29 ms for the window's medium one)
BACK_FLOW = FlowConfig(dis_preset='fast')


@dataclass
class MountCheckConfig:
    """enabled: estimate at all; refit_every: new pairs between two fits at most (the first fit comes at the fit's
    min_pairs, each next one after twice as many new pairs as the last, up to this: a fit on 91 pairs takes 1 s of
    a core here, on 200 about 2 s); max_pairs: pairs kept (the newest);
    history_s: odometry kept behind the newest frame (s); warn_sigmas: how many sigmas from the mount in use
    (and from a zero offset) an estimate must be to warn; warn_rotation_deg / warn_translation_m / warn_offset_ms:
    and at least this far; warn_min_pairs: no WARN from a fit on fewer pairs (the first fits, on a few pairs, are
    reported in /diagnostics only: on the rendered hospital the first estimate moved by 0.5 deg by the next);
    background: fit on a thread of its own (False: in the caller, as the tools do);
    fit: the fit's settings (searched offsets, robust loss, sigma floors)."""
    enabled: bool = True
    refit_every: int = 128
    max_pairs: int = 200
    history_s: float = 300.0
    warn_sigmas: float = 4.0
    warn_rotation_deg: float = 0.5
    warn_translation_m: float = 0.02
    warn_offset_ms: float = 10.0
    warn_min_pairs: int = 20
    background: bool = True
    fit: MountFitConfig = field(default_factory=MountFitConfig)


@dataclass
class MountCheckStatus:
    """What the mount check knows: pairs measured and refused (by reason), fits made, the last fit (None before
    one), and whether the rotation, the translation or the offset is confidently off (what the WARN said)."""
    enabled: bool
    pairs: int = 0
    pairs_refused: Dict[str, int] = field(default_factory=dict)
    fits: int = 0
    fit: Optional[MountFit] = None
    rotation_off: bool = False
    translation_off: bool = False
    offset_off: bool = False

    def as_dict(self) -> Dict[str, Any]:
        out: Dict[str, Any] = {'enabled': self.enabled, 'pairs': self.pairs, 'pairs_refused': dict(self.pairs_refused),
                               'fits': self.fits, 'rotation_off': self.rotation_off,
                               'translation_off': self.translation_off, 'offset_off': self.offset_off}
        if self.fit is not None:
            out['fit'] = fit_dict(self.fit)
        return out


def fit_dict(f: MountFit) -> Dict[str, Any]:
    """A fit as JSON-ready numbers (deg, mm, ms; None where not estimated)."""
    def finite(v):
        return float(v) if math.isfinite(float(v)) else None
    return {'ok': f.ok, 'reason': f.reason, 'pairs': f.pairs, 'matches': f.matches, 'median_px': f.median_px,
            'rotvec_deg': [float(v) for v in np.degrees(f.rotvec_rad)], 'angle_deg': f.angle_deg,
            'sigma_rot_deg': [finite(v) for v in f.sigma_rot_deg],
            'translation_mm': [1e3 * float(v) for v in f.translation_m],
            'sigma_trans_mm': [finite(1e3 * v) for v in f.sigma_trans_m],
            'time_offset_ms': 1e3 * f.time_offset_s, 'sigma_time_ms': finite(1e3 * f.sigma_time_s)}


def pair_matches(key_a: float, key_b: float, pa_n2: np.ndarray, pb_n2: np.ndarray, K_33: np.ndarray,
                 flow_hw2: Optional[np.ndarray] = None, gray_a: Optional[np.ndarray] = None,
                 gray_b: Optional[np.ndarray] = None) -> Tuple[Optional[PairMatchSet], Optional[str]]:
    """(the pair's matches as the fit scores them, None) or (None, why not in a word). ``key_a`` / ``key_b``: the
    two images' stamps (s); ``pa_n2`` in the first, ``pb_n2`` in the second (pixels of ``K_33``). A flow pair
    (``flow_hw2`` given) keeps the matches the flow back from ``gray_b`` to ``gray_a`` returns (module doc); a
    flow pair without its images is refused."""
    pa, pb = np.asarray(pa_n2, np.float64), np.asarray(pb_n2, np.float64)
    if flow_hw2 is not None:
        if gray_a is None or gray_b is None:
            return None, 'no_images'
        back = dense_flow(gray_b, gray_a, BACK_FLOW)
        keep = round_trip_px(back, pa, pb) < ROUND_TRIP_PX
        pa, pb = pa[keep], pb[keep]
    if len(pa) < MountFitConfig().min_matches:
        return None, 'few_matches'
    return normalised_matches(key_a, key_b, pa, pb, K_33, MAX_PAIR_POINTS), None


class MountCheck:
    """The live mount check (module doc). ``observe_frame`` per pushed frame, ``observe_window`` per refinement
    result; ``status`` says what it knows. ``logger``: where the WARN goes; ``mount_text``: a function of the fit
    that names what to set (the node's, which knows the mount in use), else the rotation is named alone."""

    def __init__(self, config: Optional[MountCheckConfig] = None, logger=None, mount_text=None):
        self.config = config or MountCheckConfig()
        self.log = logger or LOG
        self.mount_text = mount_text
        self.track = PoseTrack()
        self._pairs: List[PairMatchSet] = []
        self._thread: Optional[threading.Thread] = None
        self._lock = threading.Lock()
        self._seen: Set[Tuple[Hashable, Hashable]] = set()
        self._new = 0
        self._next_fit = self.config.fit.min_pairs
        self._warned_rotation: Optional[np.ndarray] = None
        self._warned_offset: Optional[float] = None
        self.status = MountCheckStatus(enabled=self.config.enabled)

    def observe_frame(self, stamp_s: float, T_world_cam_44: np.ndarray) -> None:
        """A frame the estimator took, with the pose it used."""
        if not self.config.enabled:
            return
        self.track.add(float(stamp_s), T_world_cam_44)
        self.track.forget_before(float(stamp_s) - self.config.history_s)

    def observe_window(self, result) -> None:
        """A refinement window's result: its pairs not measured before are measured; a fit when enough are new."""
        if not self.config.enabled or result is None:
            return
        images = getattr(result, 'match_images', None) or {}
        for m in getattr(result, 'matches', None) or []:
            key = (m.key_a, m.key_b)
            if key in self._seen or (m.key_b, m.key_a) in self._seen:
                continue
            self._seen.add(key)
            pair, why = pair_matches(m.key_a, m.key_b, m.pa_n2, m.pb_n2, m.K_33, m.flow_hw2, images.get(m.key_a),
                                     images.get(m.key_b))
            if pair is None:
                self.status.pairs_refused[why] = self.status.pairs_refused.get(why, 0) + 1
                continue
            self._pairs.append(pair)
            self._new += 1
        del self._pairs[:-self.config.max_pairs]
        oldest = self.track.span[0]
        self._seen = {k for k in self._seen if float(k[0]) >= oldest and float(k[1]) >= oldest}
        self.status.pairs = len(self._pairs)
        if self._new >= self._next_fit:
            self.refit()

    def refit(self, wait: bool = False) -> None:
        """Fit on the pairs kept (also when fewer than refit_every are new): on a thread of its own with
        ``background`` unless ``wait``; a fit still running is not started twice."""
        self._new = 0
        self._next_fit = min(self.config.refit_every, 2 * self._next_fit)
        if self._thread is not None and self._thread.is_alive():
            if not wait:
                return
            self._thread.join()
        pairs, track = list(self._pairs), copy.deepcopy(self.track)
        if wait or not self.config.background:
            self._fit(pairs, track)
            return
        self._thread = threading.Thread(target=self._fit, args=(pairs, track), name='mount_check', daemon=True)
        self._thread.start()

    def wait(self) -> None:
        """Wait for a fit in progress."""
        if self._thread is not None:
            self._thread.join()

    def _fit(self, pairs, track) -> None:
        try:
            fit = fit_mount(pairs, track, self.config.fit)
        except Exception as exc:      # a fit never stops the stream: it says why it has no estimate
            fit = MountFit(False, f'the fit failed: {type(exc).__name__}: {exc}')
        with self._lock:
            self.status.fits += 1
            self.status.fit = fit
            self._judge(fit)

    def _judge(self, fit: MountFit) -> None:
        cfg, st = self.config, self.status
        if not fit.ok:
            st.rotation_off = st.translation_off = st.offset_off = False
            return
        st.rotation_off = fit.rotation_significance() >= cfg.warn_sigmas and fit.angle_deg >= cfg.warn_rotation_deg
        sig_t = fit.sigma_trans_m
        norm_t = float(np.linalg.norm(fit.translation_m))
        st.translation_off = bool(np.all(np.isfinite(sig_t)) and norm_t >= cfg.warn_translation_m
                                  and norm_t >= cfg.warn_sigmas * float(np.max(sig_t)))
        offset_ms, sigma_ms = 1e3 * fit.time_offset_s, 1e3 * fit.sigma_time_s
        st.offset_off = (math.isfinite(sigma_ms) and abs(offset_ms) >= cfg.warn_sigmas * sigma_ms
                         and abs(offset_ms) >= cfg.warn_offset_ms)
        mount = np.r_[fit.rotvec_rad, fit.translation_m]
        moved_mount = (self._warned_rotation is None
                       or math.degrees(float(np.linalg.norm(mount[:3] - self._warned_rotation[:3])))
                       >= cfg.warn_rotation_deg
                       or float(np.linalg.norm(mount[3:] - self._warned_rotation[3:])) >= cfg.warn_translation_m)
        moved_off = self._warned_offset is None or abs(fit.time_offset_s - self._warned_offset) * 1e3 >= \
            cfg.warn_offset_ms
        if fit.pairs < cfg.warn_min_pairs:
            return
        if (st.rotation_off or st.translation_off) and moved_mount:
            self._warned_rotation = mount
            self.log.warning(f'mount check: {mount_text(fit)}'
                             + (f'; {self.mount_text(fit)}' if self.mount_text is not None else ''))
        if st.offset_off and moved_off:
            self._warned_offset = fit.time_offset_s
            self.log.warning(f'mount check: {offset_text(fit)}')


def mount_text(fit: MountFit) -> str:
    """The mount estimate in words: angle, rotation vector and translation with their sigmas, pairs."""
    v, s = np.degrees(fit.rotvec_rad), fit.sigma_rot_deg
    text = (f"the images say the camera is turned {fit.angle_deg:.2f} deg from the mount in use (rotation vector "
            f"[{v[0]:+.2f}, {v[1]:+.2f}, {v[2]:+.2f}] +- [{s[0]:.2f}, {s[1]:.2f}, {s[2]:.2f}] deg about the camera's "
            f"x, y, z")
    st = fit.sigma_trans_m
    if np.all(np.isfinite(st)):
        t = 1e3 * fit.translation_m
        text += (f'; shifted [{t[0]:+.0f}, {t[1]:+.0f}, {t[2]:+.0f}] +- [{1e3 * st[0]:.0f}, {1e3 * st[1]:.0f}, '
                 f'{1e3 * st[2]:.0f}] mm')
    else:
        text += '; its shift not observed: the camera did not turn while moving'
    return text + f'; {fit.pairs} image pairs)'


def offset_text(fit: MountFit) -> str:
    """The time offset in words and what it means."""
    ms, s = 1e3 * fit.time_offset_s, 1e3 * fit.sigma_time_s
    late = 'late' if ms >= 0 else 'early'
    return (f"time offset {ms:+.1f} +- {s:.1f} ms: the pose at an image's time is the odometry's at the image's "
            f'stamp {ms:+.0f} ms (the odometry is stamped {abs(ms):.0f} ms {late}; {fit.pairs} image pairs)')


# a recording's pairs end at the first image that turned this much (deg), moved this far (m) or is this many frames on
PAIR_TURN_DEG, PAIR_MOVE_M, PAIR_MAX_FRAMES = 5.0, 0.05, 5


def sequence_pairs(seq, poses: List[np.ndarray], every: int, progress: bool) -> list:
    """The pairs of a recording as the fit scores them (``calibrate_mount``, ``studies.mount_check``): the keyframe
    window's kind of pairs, each ``every``-th image with the next one that turned
    PAIR_TURN_DEG, moved PAIR_MOVE_M or is PAIR_MAX_FRAMES on, matched by the window's flow."""
    from scipy.spatial.transform import Rotation
    from tqdm import tqdm

    from dpv_sensor.core.flow_rotation import FlowConfig, flow_matches, match_image
    cfg = FlowConfig()
    K = np.asarray(seq.K, np.float64)
    grey: Dict[int, Any] = {}

    def image(i):
        if i not in grey:
            grey[i] = match_image(seq.image(i), K, cfg)
            for k in [k for k in grey if k < i - PAIR_MAX_FRAMES]:
                del grey[k]
        return grey[i]

    pairs = []
    n = len(seq)
    for a in tqdm(range(0, n - 1, max(1, every)), desc='pairs', disable=not progress, unit='pair'):
        b = a + 1
        for b in range(a + 1, min(n, a + PAIR_MAX_FRAMES + 1)):
            T_b_a = np.linalg.inv(poses[b]) @ poses[a]
            if (math.degrees(Rotation.from_matrix(T_b_a[:3, :3]).magnitude()) >= PAIR_TURN_DEG
                    or float(np.linalg.norm(T_b_a[:3, 3])) >= PAIR_MOVE_M):
                break
        (ga, Kg), (gb, _) = image(a), image(b)
        m = flow_matches(ga, gb, Kg, cfg)
        pair, _why = pair_matches(float(seq.stamp(a)), float(seq.stamp(b)), m.pa_n2, m.pb_n2, Kg, m.flow_hw2, ga, gb)
        if pair is not None:
            pairs.append(pair)
    return pairs
