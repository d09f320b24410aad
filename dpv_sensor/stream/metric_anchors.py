"""The reference keyframe's metric anchors and what they do to its published depth (layer 3).

The window refiner already matches the reference with its nearest sources (optical flow at the camera's resolution,
or SIFT's inliers: :class:`~dpv_sensor.stream.window_refiner_config.PairMatches`) and refines their metric poses;
:func:`reference_anchors` triangulates those matches with the refined poses (:mod:`dpv_sensor.core.anchors`: each
kept anchor has parallax, a small reprojection error in both views, lies in front of both cameras and carries a σ
of log depth from the pixel noise and the odometry's uncertainty of the pair). Nothing is detected or matched
twice. A camera that turns in place gives rays that do not meet at an angle: no anchors, and no change.

:class:`AnchorAligner` holds the keyframe's depth to them (``depth_anchors``):

- ``scale``: one robust, σ-weighted log scale (Huber IRLS) multiplies the depth;
- ``dense``: a depth-aware scale map (a bilateral grid over the image and the depth: a pixel is corrected by the
  anchors near it in the image *and* in depth, and keeps the network's depth where none is), so a region that the
  networks put at the wrong depth is corrected where anchors are, and a confident wrong region is caught;
- ``off``: the depth as the networks give it (the anchors are still counted, so ``/diagnostics`` shows what they
  would say).

Either way the confidence becomes that of the corrected depth: widened by the fit's uncertainty (a scale known to
a few percent changes little; a poorly supported node of the map widens more) and, where the anchors say the
depth was off by more than their σ explains, by the size of that disagreement — a surface the networks put at twice
its depth is no longer published as confident even where the map cannot fully mend it. Keyframes with fewer than
``min_anchors`` usable anchors are published unchanged, bit for bit.

Which map says where the networks are overruled (``anchor_judge``): ``cautious``, the correcting map itself, whose
pull towards no correction outweighs a few dozen anchors; or ``counted``, a second map that counts each anchor at
its own weight (:func:`~dpv_sensor.core.anchors.fit_scale_map` with ``in_anchor_weights``) and corrects what it
overrules by its own map. Where the networks are overruled, ``anchor_fallback: classical`` blends in the classical
sweep's depth of the keyframe (:mod:`dpv_sensor.stream.classical_fallback`), held to the same anchors.

:class:`AnchorStatus` counts what happened (keyframes checked / aligned, anchors, rejected candidates by reason,
the last scale and its σ, pixels whose correction was beyond the anchors' σ) for ``/diagnostics``;
:func:`hold_to_anchors` is the estimator's hook (its tensors in and out). numpy and torch; no ROS.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Callable, Dict, Hashable, Optional, Tuple

import cv2
import numpy as np
import torch

from dpv_sensor.core import anchors as anchor_math
from dpv_sensor.core.anchors import AnchorConfig, Anchors

__all__ = ['ANCHOR_MODES', 'JUDGES', 'NEEDS_WINDOW', 'AnchorStatus', 'AnchorReport', 'AnchorAligner',
           'reference_anchors', 'hold_to_anchors', 'belief_log_scale']

#: the ``depth_anchors`` choices
ANCHOR_MODES = ('off', 'scale', 'dense')

#: the estimator's note when anchors are asked for without the refinement window they are made from
NEEDS_WINDOW = ('depth_anchors={mode} needs pose_refinement=window (its matches and poses): the depth is not checked '
                'against anchors')

#: a correction counts as a disagreement of the network with its anchors beyond their σ above this many σ
OVERRULE_SIGMAS = 3.0

#: the ``anchor_judge`` choices: which map decides where the networks are overruled
JUDGES = ('cautious', 'counted')

#: the judge's bins of log depth over the depth planes: about 1.25x a bin over 0.3-8 m, so that a surface and
#: another at twice its depth do not share a bin after the grid's blur (the cautious map's 8 bins are 1.6x)
JUDGE_DEPTH_BINS = 16

#: the judge overrules only where its support is at least this many anchors' weight (anchors whose σ is the depth's
#: own structure error, ``depth_sigma_log``)
JUDGE_MIN_ANCHORS = 3.0


def reference_anchors(result, ref_key: Hashable, config: AnchorConfig = AnchorConfig()) -> Anchors:
    """The anchors of the reference keyframe ``ref_key`` from a window refiner's result (its ``matches`` and
    refined ``T_world_cam``), pixels at the first part's resolution; empty without matches.

    The flow's pairs chain into tracks: the sampled pixels of the oldest keyframe whose chain of flows reaches the
    reference follow the dense flows from keyframe to keyframe (older to newer, as the window measured them) to the
    newest; each track's pixels in its first and last views are refined by Lucas-Kanade from its pixel in the
    reference image (checked by tracking back), and it is triangulated from its first and its last view (the
    longest baseline) and checked in those and in the reference. SIFT's pairs with the reference are triangulated
    as they are."""
    poses = result.T_world_cam
    if ref_key not in poses:
        return Anchors.empty()
    flows: Dict[Hashable, object] = {}
    parts = []
    newest = {}                  # one set of matches per pair: the last the window measured
    for m in getattr(result, 'matches', None) or []:
        newest[frozenset((m.key_a, m.key_b))] = m
    for m in newest.values():
        if m.key_a not in poses or m.key_b not in poses:
            continue
        if m.flow_hw2 is not None and m.key_a < m.key_b:
            flows[m.key_a] = m
        elif ref_key in (m.key_a, m.key_b):
            if m.key_a == ref_key:
                p_ref, p_src, src = m.pa_n2, m.pb_n2, m.key_b
            else:
                p_ref, p_src, src = m.pb_n2, m.pa_n2, m.key_a
            T_src_ref = np.linalg.inv(poses[src]) @ poses[ref_key]
            parts.append(anchor_math.triangulate_pair(p_ref, p_src, m.K_33, T_src_ref, m.sigma_rot_rad,
                                                      m.sigma_trans_m, len(parts), config))
    track = _longest_track(flows, ref_key, config.max_tracks)
    if track is not None:
        keys = [k for k, _p in track]
        r = keys.index(ref_key)
        # the views that matter: the first and the last (the triangulation's baseline) and the reference
        views = sorted({0, r, len(keys) - 1})
        steps = [flows[k] for k in keys[:-1]]
        sigma_rot = math.sqrt(sum(m.sigma_rot_rad ** 2 for m in steps))
        sigma_trans = math.sqrt(sum(m.sigma_trans_m ** 2 for m in steps))
        images = getattr(result, 'match_images', None) or {}
        points = [track[v][1] for v in views]
        rv = views.index(r)
        if all(keys[v] in images for v in views):
            points = [p if i == rv else anchor_math.refine_tracks(images[ref_key], points[rv], images[keys[v]], p,
                                                                  config)
                      for i, (v, p) in enumerate(zip(views, points))]
        parts.append(anchor_math.triangulate_track(points, [poses[keys[v]] for v in views], steps[0].K_33, rv,
                                                   sigma_rot, sigma_trans, len(parts), config))
    return anchor_math.concat_anchors(parts)


def _longest_track(flows: Dict[Hashable, object], ref_key: Hashable, max_tracks: int):
    """The tracks of the longest chain of flows that passes through the reference: they start at the sampled pixels
    of the oldest keyframe whose chain reaches the reference (at most ``max_tracks`` of them, evenly spread) and
    follow the flows to the newest; None without such a chain."""
    for start in sorted(flows):
        if start > ref_key:
            return None
        k = start
        while k in flows and k < ref_key:
            k = flows[k].key_b
        if k == ref_key or (start == ref_key and k in flows):
            return _flow_track(flows, start, max_tracks)
    return None


def _flow_track(flows: Dict[Hashable, object], start: Hashable, max_tracks: int):
    """[(key, pixels (n, 2))] of the tracks that start at keyframe ``start``'s sampled pixels (every n-th, at most
    ``max_tracks``) and follow the chain of flows from it (NaN once a track leaves the image)."""
    m = flows[start]
    step = max(1, -(-len(m.pa_n2) // max(1, max_tracks)))
    track = [(start, m.pa_n2[::step]), (m.key_b, m.pb_n2[::step])]
    while track[-1][0] in flows:
        nxt = flows[track[-1][0]]
        p = track[-1][1]
        F = nxt.flow_hw2
        h, w = F.shape[:2]
        x, y = p[:, 0].astype(np.float32), p[:, 1].astype(np.float32)
        d = cv2.remap(F, x[None], y[None], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                      borderValue=(np.nan, np.nan))[0].astype(np.float64)
        q = p + d
        out = ~((q[:, 0] >= 0) & (q[:, 0] <= w - 1) & (q[:, 1] >= 0) & (q[:, 1] <= h - 1))
        q[out] = np.nan
        track.append((nxt.key_b, q))
    return track


@dataclass
class AnchorReport:
    """One keyframe: anchors kept and candidates rejected by reason; those with a depth to compare (used) and the
    fit's inliers; the global scale (None: no fit) and its σ (log); what was applied ('none', 'scale', 'dense');
    pixels whose depth moved (the disagreement beyond correction_sigmas) and pixels where it exceeded
    OVERRULE_SIGMAS (overruled); of those, the pixels where the classical sweep's depth outweighed the networks'
    (fallback_pixels) and what the fallback did ('blended' or why not, None: not asked); why nothing was
    applied."""
    anchors: int = 0
    rejected: Dict[str, int] = field(default_factory=dict)
    used: int = 0
    inliers: int = 0
    scale: Optional[float] = None
    sigma: Optional[float] = None
    applied: str = 'none'
    corrected_pixels: int = 0
    overruled_pixels: int = 0
    fallback_pixels: int = 0
    fallback: Optional[str] = None
    reason: Optional[str] = None


@dataclass
class AnchorStatus:
    """Since the start: the mode; keyframes checked (a window to triangulate from) and aligned (a fit applied);
    keyframes vetoed (the poses cannot anchor them: the images disagree with the odometry's directions) and
    keyframes whose anchors did not agree on a scale (not applied);
    keyframes where some region disagreed with its anchors beyond their σ and the pixels that were; keyframes
    where the classical sweep was blended in there and the pixels where it outweighed the networks; anchors kept
    and candidates rejected by reason; the last keyframe's report."""
    mode: str = 'off'
    keyframes_checked: int = 0
    keyframes_aligned: int = 0
    keyframes_overruled: int = 0
    keyframes_vetoed: int = 0
    keyframes_disagreeing: int = 0
    pixels_overruled: int = 0
    keyframes_fallback: int = 0
    pixels_fallback: int = 0
    anchors: int = 0
    rejected: Dict[str, int] = field(default_factory=dict)
    last: Optional[AnchorReport] = None

    def as_dict(self) -> Dict:
        return dataclasses.asdict(self)


class AnchorAligner:
    """Holds each keyframe's depth to its anchors (module doc). ``mode``: one of :data:`ANCHOR_MODES`;
    ``ratio``: the confidence's band (×ratio); ``depth_range``: (d_min, d_max) of the depth planes, outside which
    anchors are not compared (None: all are)."""

    def __init__(self, mode: str = 'off', config: AnchorConfig = AnchorConfig(), ratio: float = 1.25,
                 depth_range: Optional[Tuple[float, float]] = None, judge: str = 'cautious'):
        if mode not in ANCHOR_MODES:
            raise ValueError(f'depth_anchors must be one of {ANCHOR_MODES}, not {mode!r}')
        if judge not in JUDGES:
            raise ValueError(f'anchor_judge must be one of {JUDGES}, not {judge!r}')
        self.mode = mode
        self.judge = judge
        self.config = config
        self.ratio = float(ratio)
        self.depth_range = depth_range
        self.status = AnchorStatus(mode=mode)
        self._min_support = JUDGE_MIN_ANCHORS / config.depth_sigma_log ** 2

    @property
    def _counted(self) -> bool:
        """The counted judge decides (dense maps only)."""
        return self.judge == 'counted' and self.mode == 'dense'

    def _log_range(self, depth_hw: np.ndarray) -> Tuple[float, float]:
        """The log depths the scale map spans: the depth planes' range, else the map's own 1st to 99th
        percentile."""
        if self.depth_range is not None:
            return math.log(self.depth_range[0]), math.log(self.depth_range[1])
        d = depth_hw[np.isfinite(depth_hw) & (depth_hw > 0)]
        lo, hi = np.percentile(d, [1, 99]) if d.size else (1.0, 2.0)
        return math.log(lo), math.log(max(hi, lo * 1.01))

    def apply(self, depth_hw: np.ndarray, conf_hw: np.ndarray, K_depth_33: np.ndarray, anchors: Optional[Anchors],
              veto: Optional[str] = None, fallback: Optional[Callable[[], Optional[Tuple[np.ndarray, np.ndarray]]]]
              = None) -> Tuple[np.ndarray, np.ndarray, AnchorReport]:
        """(depth, confidence, report) of one keyframe: ``depth_hw`` (m, NaN/0 = none) and ``conf_hw`` at the
        size of ``K_depth_33``; ``anchors`` None: none to check against, ``veto`` saying why (default: no window
        to triangulate from). ``fallback``: called only when some pixels are overruled, the classical sweep's
        (depth, confidence) of the keyframe at the same size (or None), blended in there. The arrays are returned
        as given (the same objects) when nothing is applied."""
        st = self.status
        if anchors is None:
            rep = AnchorReport(reason=veto or 'no refinement window (pose_refinement off or no matches yet)')
            st.last = rep
            if veto is not None:
                st.keyframes_vetoed += 1
            return depth_hw, conf_hw, rep
        cfg = self.config
        st.keyframes_checked += 1
        st.anchors += len(anchors)
        for k, v in anchors.rejected.items():
            st.rejected[k] = st.rejected.get(k, 0) + int(v)
        rep = AnchorReport(anchors=len(anchors), rejected=dict(anchors.rejected))
        st.last = rep
        rep.rejected.setdefault('depth_edge', 0)
        if len(anchors) < cfg.min_anchors:
            rep.reason = f'too few anchors ({len(anchors)} < {cfg.min_anchors})'
            return depth_hw, conf_hw, rep
        K = np.asarray(K_depth_33, np.float64)
        x = np.c_[anchors.uv_n2, np.ones(len(anchors))] @ np.linalg.inv(anchors.K_33).T @ K.T
        uv = x[:, :2]
        log_ratio = self._log_ratios(depth_hw, anchors, uv, rep)
        fit = anchor_math.fit_log_scale(log_ratio, anchors, cfg)
        if fit is None:
            rep.used = int(np.isfinite(log_ratio).sum())
            rep.reason = f'too few anchors on the depth ({rep.used} < {cfg.min_anchors})'
            return depth_hw, conf_hw, rep
        rep.used, rep.inliers, rep.scale, rep.sigma = fit.used, fit.inliers, fit.scale, fit.sigma
        if self.mode == 'off':
            rep.reason = "depth_anchors is 'off'"
            return depth_hw, conf_hw, rep
        if not self._counted and fit.inliers < cfg.min_inlier_fraction * fit.used:
            rep.reason = (f'the anchors do not agree on a scale ({fit.inliers} of {fit.used} within '
                          f'{cfg.huber_k:g} sigma)')
            st.keyframes_disagreeing += 1
            return depth_hw, conf_hw, rep
        held = self._hold(depth_hw, conf_hw, log_ratio, anchors, uv, fit)
        if self._counted:
            # the map may say different things in different regions (a near desk put too far, the room right), but
            # each anchor must agree with what it says where the anchor is: scattered anchors (poses that do not
            # explain the images, bad matches) correct nothing
            agree = self._agreeing(held.judge_hw, log_ratio, anchors, uv)
            if agree < cfg.min_inlier_fraction * fit.used:
                rep.reason = (f'the anchors do not agree with a scale map ({agree} of {fit.used} within '
                              f'{cfg.huber_k:g} sigma of it)')
                st.keyframes_disagreeing += 1
                return depth_hw, conf_hw, rep
        valid = np.isfinite(depth_hw) & (depth_hw > 0)
        overruled = held.overruled_hw & valid
        rep.overruled_pixels = int(overruled.sum())
        rep.corrected_pixels = int(((held.excess_hw > 0) & valid).sum())
        rep.applied = self.mode
        st.keyframes_aligned += 1
        depth, conf = held.depth_hw, held.conf_hw
        if rep.overruled_pixels:
            st.keyframes_overruled += 1
            st.pixels_overruled += rep.overruled_pixels
            if fallback is not None and self.mode == 'dense':
                # a region's second opinion (with 'scale' the whole image would be one region: not blended)
                depth, conf = self._second_opinion(depth, conf, overruled, anchors, uv, fallback, rep)
        return depth, conf, rep

    def _log_ratios(self, depth_hw: np.ndarray, anchors: Anchors, uv_n2: np.ndarray,
                    rep: Optional[AnchorReport] = None) -> np.ndarray:
        """log(anchor depth / depth at its pixel) of every anchor; NaN at the depth map's edges, outside the depth
        planes and where the map has no depth. With ``rep`` the two rejections are counted (its and the
        status')."""
        d_at = anchor_math.sample_depth(depth_hw, uv_n2)
        H, W = depth_hw.shape
        ix = np.clip(np.rint(uv_n2[:, 0]), 0, W - 1).astype(np.int64)
        iy = np.clip(np.rint(uv_n2[:, 1]), 0, H - 1).astype(np.int64)
        edge = anchor_math.depth_edge_mask(depth_hw, self.config.edge_log_range)[iy, ix] & np.isfinite(d_at)
        d_at[edge] = np.nan
        out = np.zeros(len(d_at), bool)
        if self.depth_range is not None:
            # anchors outside the depth planes' range: the map cannot hold them, so they say nothing about it
            out = ((anchors.depth_n < self.depth_range[0]) | (anchors.depth_n > self.depth_range[1])) & \
                np.isfinite(d_at)
            d_at[out] = np.nan
        if rep is not None:
            st = self.status
            rep.rejected['depth_edge'] = int(edge.sum())
            st.rejected['depth_edge'] = st.rejected.get('depth_edge', 0) + int(edge.sum())
            if self.depth_range is not None:
                rep.rejected['out_of_planes'] = int(out.sum())
                st.rejected['out_of_planes'] = st.rejected.get('out_of_planes', 0) + int(out.sum())
        with np.errstate(divide='ignore', invalid='ignore'):
            return np.log(anchors.depth_n) - np.log(d_at)

    def _agreeing(self, map_hw: np.ndarray, log_ratio: np.ndarray, anchors: Anchors, uv_n2: np.ndarray) -> int:
        """How many anchors with a depth to compare lie within huber_k of their σ (and the depth's own structure
        error) of what ``map_hw`` says at their pixel."""
        H, W = map_hw.shape
        ix = np.clip(np.rint(uv_n2[:, 0]), 0, W - 1).astype(np.int64)
        iy = np.clip(np.rint(uv_n2[:, 1]), 0, H - 1).astype(np.int64)
        s = np.sqrt(anchors.sigma_ind_n ** 2 + anchors.sigma_pair_n ** 2 + self.config.depth_sigma_log ** 2)
        with np.errstate(invalid='ignore'):
            return int((np.abs(log_ratio - map_hw[iy, ix]) <= self.config.huber_k * s).sum())

    def _hold(self, depth_hw: np.ndarray, conf_hw: np.ndarray, log_ratio: np.ndarray, anchors: Anchors,
              uv_n2: np.ndarray, fit) -> '_Held':
        """One depth map held to its anchors (the mode's scale or map): the corrected depth and confidence, the
        correction's size beyond the anchors' σ, and where the disagreement exceeded OVERRULE_SIGMAS."""
        cfg = self.config
        if self.mode == 'scale':
            log_map = np.full(depth_hw.shape, fit.log_scale)
            sigma_map = np.full(depth_hw.shape, fit.sigma)
        else:
            log_range = self._log_range(depth_hw)
            smap = anchor_math.fit_scale_map(log_ratio, anchors, uv_n2, depth_hw, fit, log_range, cfg)
            log_map, sigma_map = smap.log_scale_hw, smap.sigma_hw
        # the anchor set's own systematic error (flow that underestimates a large displacement, a scene the poses
        # do not quite explain) is shared by every anchor of a keyframe and no count of anchors averages it away
        sigma_map = np.hypot(sigma_map, cfg.bias_sigma_log)
        # without the counted judge the cautious map decides alone (nothing judged)
        judge_map, judge_sigma, judged = log_map, sigma_map, np.zeros(depth_hw.shape, bool)
        if self._counted:
            # the judge: the same map with the support counted in the anchors' own weights, so a region whose
            # anchors all say the depth is off is heard (the cautious map's prior outweighs a few dozen anchors),
            # with finer bins of depth (a coarser image grid would carry a region's verdict a whole cell beyond its
            # anchors: onto a wall that happens to stand where the doubled desk seems to be)
            judge = anchor_math.fit_scale_map(log_ratio, anchors, uv_n2, depth_hw, fit, log_range,
                                              dataclasses.replace(cfg, grid_depth_bins=JUDGE_DEPTH_BINS),
                                              in_anchor_weights=True)
            judge_map, judge_sigma = judge.log_scale_hw, np.hypot(judge.sigma_hw, cfg.bias_sigma_log)
            # a disagreement beyond what the anchors' σ explains says the depth was wrong there by about its size:
            # it is overruled, corrected by the judge's map less its σ, and as uncertain as the disagreement was
            # large; only where the anchors are (at least JUDGE_MIN_ANCHORS of support: the blur's tails judge
            # nothing)
            judged = (np.abs(judge_map) > OVERRULE_SIGMAS * judge_sigma) & (judge.support_hw >= self._min_support)
        # elsewhere a check first: the depth is corrected only by as much as the cautious map disagrees with it
        # beyond correction_sigmas of its σ (soft threshold), so a network that agrees with its anchors is left
        # alone; where the depth moved at all, it is as uncertain as the correction, and where even the cautious
        # map disagrees beyond OVERRULE_SIGMAS (few anchors far off), as uncertain as the disagreement
        cautious = np.abs(log_map) > OVERRULE_SIGMAS * sigma_map
        excess = np.where(judged, np.abs(judge_map) - cfg.correction_sigmas * judge_sigma,
                          np.maximum(np.abs(log_map) - cfg.correction_sigmas * sigma_map, 0.0))
        applied = np.where(judged, np.sign(judge_map), np.sign(log_map)) * excess
        widen = np.where(judged, np.hypot(judge_sigma, np.abs(judge_map)),
                         np.where(cautious, np.hypot(sigma_map, np.abs(log_map)),
                                  np.where(excess > 0, sigma_map, 0.0)))
        overruled = judged | cautious
        valid = np.isfinite(depth_hw) & (depth_hw > 0)
        depth = np.where(valid, depth_hw * np.exp(applied), depth_hw).astype(depth_hw.dtype)
        conf = conf_hw.copy()
        moved = widen > 0
        conf[moved] = anchor_math.widened_confidence(conf_hw[moved], widen[moved], self.ratio)
        return _Held(depth, conf, excess, overruled, judge_map)

    def _second_opinion(self, depth_hw: np.ndarray, conf_hw: np.ndarray, overruled_hw: np.ndarray, anchors: Anchors,
                        uv_n2: np.ndarray, fallback, rep: AnchorReport) -> Tuple[np.ndarray, np.ndarray]:
        """Where the networks were overruled, the classical sweep's depth (``fallback()``: its depth and
        confidence at the same pixels, or None), held to the same anchors the same way, blended in by confidence
        (:func:`~dpv_sensor.core.anchors.blend_log_depth`): a region the sweep explains better than the networks
        takes the sweep's depth; where the sweep has no texture to go by, the networks' corrected depth stays."""
        st = self.status
        got = fallback()
        if got is None:
            rep.fallback = 'no classical depth for this keyframe'
            return depth_hw, conf_hw
        dc, cc = got
        if dc.shape != depth_hw.shape or cc.shape != depth_hw.shape:
            rep.fallback = f'the classical depth is {dc.shape}, not {depth_hw.shape}'
            return depth_hw, conf_hw
        log_ratio = self._log_ratios(dc, anchors, uv_n2)
        fit = anchor_math.fit_log_scale(log_ratio, anchors, self.config)
        if fit is None:
            rep.fallback = 'too few anchors on the classical depth'
            return depth_hw, conf_hw
        held = self._hold(dc, np.asarray(cc, np.float32), log_ratio, anchors, uv_n2, fit)
        agree = self._agreeing(held.judge_hw, log_ratio, anchors, uv_n2) if self._counted else fit.inliers
        if agree < self.config.min_inlier_fraction * fit.used:
            rep.fallback = f'the anchors do not agree with the classical depth either ({agree} of {fit.used})'
            return depth_hw, conf_hw
        region = overruled_hw & np.isfinite(held.depth_hw) & (held.depth_hw > 0) & (held.conf_hw > 0)
        if not region.any():
            rep.fallback = 'the classical depth has nothing where the networks are overruled'
            return depth_hw, conf_hw
        d, c, w = anchor_math.blend_log_depth(depth_hw[region].astype(np.float64), conf_hw[region],
                                              held.depth_hw[region].astype(np.float64), held.conf_hw[region],
                                              self.ratio)
        depth, conf = depth_hw.copy(), conf_hw.copy()
        depth[region] = d
        conf[region] = c
        rep.fallback_pixels = int((w > 0.5).sum())
        rep.fallback = 'blended'
        st.keyframes_fallback += 1
        st.pixels_fallback += rep.fallback_pixels
        return depth, conf


@dataclass
class _Held:
    """One depth map held to its anchors: the corrected depth and confidence, the correction beyond the anchors' σ
    (log), where the disagreement exceeded OVERRULE_SIGMAS, and the judge's log-scale map."""
    depth_hw: np.ndarray
    conf_hw: np.ndarray
    excess_hw: np.ndarray
    overruled_hw: np.ndarray
    judge_hw: np.ndarray


def hold_to_anchors(aligner: AnchorAligner, refiner, result, ref_key: float, K_b33_t, depth_bhw, conf_bhw,
                    fallback=None, belief=None):
    """The estimator's hook: (depth, confidence, report) of a keyframe, tensors (1, H, W) at the size of
    ``K_b33_t``, held to the anchors that the window refiner's last ``result`` triangulates for ``ref_key``.
    Unchanged tensors without a refined window or under the veto (the refiner's ``direction_ratio`` above its
    threshold: the images contradict the odometry's directions); nothing computed (report None) with mode 'off'.
    ``fallback``: :meth:`AnchorAligner.apply`'s. ``belief``: a :class:`~dpv_sensor.core.filter.DPVFilter` whose
    belief takes the same correction (``anchor_target: belief``; None: the published depth alone)."""
    if aligner.mode == 'off':
        return depth_bhw, conf_bhw, None
    anchors, veto = None, None
    ratio = getattr(refiner, 'direction_ratio', None)
    if ratio is not None and ratio[0] > ratio[1]:
        # the window takes SIFT's rotations because the images disagree with the odometry's translation directions:
        # poses that do not explain the images triangulate biased points
        veto = (f"the images disagree with the odometry's translation directions (direction ratio {ratio[0]:.3f} > "
                f'{ratio[1]:g}): its poses cannot anchor the depth')
    elif result is not None and ref_key in getattr(result, 'T_world_cam', {}):
        anchors = reference_anchors(result, ref_key, aligner.config)
    d = depth_bhw[0].detach().float().cpu().numpy()
    c = conf_bhw[0].detach().float().cpu().numpy()
    d2, c2, report = aligner.apply(d, c, K_b33_t.detach().double().cpu().numpy(), anchors, veto, fallback)
    if d2 is d:
        return depth_bhw, conf_bhw, report
    held_bhw = torch.as_tensor(d2, device=depth_bhw.device, dtype=depth_bhw.dtype)[None]
    if belief is not None and belief.K_b33 is not None:
        belief.rescale_belief(belief_log_scale(depth_bhw, held_bhw, K_b33_t, belief.K_b33[0],
                                               tuple(belief.logp_bdhw.shape[-2:])))
    return held_bhw, torch.as_tensor(c2, device=conf_bhw.device, dtype=conf_bhw.dtype)[None], report


def belief_log_scale(depth_bhw: torch.Tensor, held_bhw: torch.Tensor, K_depth_33, K_belief_33,
                     belief_hw: Tuple[int, int]) -> torch.Tensor:
    """The anchors' correction of a keyframe's depth, ``log(held / depth)`` (0 where either is missing), read on
    the filter's belief grid ``K_belief_33`` of size ``belief_hw`` (the depth is on ``K_depth_33``'s): what
    :meth:`~dpv_sensor.core.filter.DPVFilter.rescale_belief` takes (``anchor_target: belief``)."""
    from dpv_sensor.core.geometry import resample_to_camera
    r = torch.log(held_bhw.double() / depth_bhw.double())
    r = torch.where(torch.isfinite(r), r, torch.zeros_like(r))
    return resample_to_camera(r[:, None], K_depth_33, K_belief_33, belief_hw)[:, 0]
