"""A keyframe's sweep geometry as the estimator uses it: which rays the window's sources see (coverage), the
measurement's depth and each source's disparity span of the x1.25 band around it, the parallax rule's weight of
the measurement, and the parallax support the new belief carries. torch and numpy only; no ROS.

The maths is :mod:`dpv_sensor.core.parallax` and :mod:`dpv_sensor.core.geometry`; this module maps the estimator's
settings and state onto it (docs/parallax.md).
"""
from __future__ import annotations

from typing import Dict, Optional, Tuple

import numpy as np
import torch

from dpv_sensor.core import dpv as dpv_ops, geometry, parallax

__all__ = ['COVERAGE_PLANES', 'coverage', 'sweep_geometry', 'parallax_weight', 'carry_support']

# planes sampled per ray for the "seen by some source view" mask (see coverage)
COVERAGE_PLANES = 16


def coverage(cfg, K_vol_b33: torch.Tensor, vol_hw, T_src_ref_n44: torch.Tensor,
             depths_d: torch.Tensor) -> torch.Tensor:
    """(1, h, w) bool: at least ``min_coverage`` of the ray's plane samples lie inside some source view.

    Evaluated on at most ``COVERAGE_PLANES`` planes spread evenly over the D planes (visibility changes
    smoothly along a ray, and all D planes would cost as much as the filter step)."""
    N = T_src_ref_n44.shape[0]
    h, w = int(vol_hw[0]), int(vol_hw[1])
    D = depths_d.shape[0]
    device = depths_d.device
    idx = torch.linspace(0, D - 1, min(D, COVERAGE_PLANES), device=device).round().long()
    ones = torch.ones(N, 1, h, w, dtype=torch.float32, device=device)
    K = K_vol_b33.float().expand(N, 3, 3)
    _, valid = geometry.plane_sweep_warp(ones, K, K, T_src_ref_n44.float(), depths_d[idx], ref_hw=(h, w))
    seen = valid.any(0).float().mean(0)                                          # h, w
    return (seen >= cfg.min_coverage)[None]


def sweep_geometry(cfg, meas_logp_bdhw: torch.Tensor, K_vol_b33: torch.Tensor, K_proc_b33: torch.Tensor,
                   T_src_ref_t: torch.Tensor, vol_hw, depths_d: torch.Tensor, readout: str
                   ) -> Optional[Tuple[torch.Tensor, torch.Tensor]]:
    """(depth (1, h, w), spans (N, 1, h, w)) at the volume resolution: the measurement's own depth estimate
    ``d``, but no nearer than its median, and per source the disparity span (processing-size pixels) of the band
    [d / 1.25, d * 1.25] (``parallax.BAND_RATIO``) around it; None when neither the parallax rule nor the pose
    uncertainty needs them."""
    if cfg.parallax_full_px <= 0 and cfg.pose_uncertainty == 'off':
        return None
    depth = dpv_ops.depth_estimate(meas_logp_bdhw.float(), depths_d, readout)
    # a wrong, too-near estimate would claim parallax it does not have: depths are taken no nearer
    # than the frame's median estimate
    depth = depth.clamp_min(float(depth.median()))
    spans = parallax.disparity_span(depth, K_vol_b33, T_src_ref_t, parallax.BAND_RATIO, src_hw=vol_hw,
                                    per_source=True)                       # N, 1, h, w
    spans = spans * float(K_proc_b33[0, 0, 0] / K_vol_b33[0, 0, 0])        # volume -> processing pixels
    return depth, spans


def parallax_weight(cfg, geom, K_proc_b33: torch.Tensor, T_src_ref_t: torch.Tensor
                    ) -> Tuple[Optional[torch.Tensor], Dict[str, float]]:
    """((1, h, w) weight in [0, 1] of this measurement per pixel, its status): ``parallax.parallax_support`` of the
    disparity span, in processing-size pixels, of the band around the measurement's depth over the window's
    sources (:func:`sweep_geometry`); (None, {}) when the parallax rule is off (``parallax_full_px`` = 0)."""
    full = float(cfg.parallax_full_px)
    if full <= 0 or geom is None:
        return None, {}
    _depth, spans = geom
    span = spans.amax(0)
    if cfg.parallax_rotation_noise > 0:
        # each source's span counts against full_px plus the pose error its rotation brings
        noise = parallax.rotation_noise_px(T_src_ref_t, float(K_proc_b33[0, 0, 0]),
                                           cfg.parallax_rotation_noise)[0]          # N
        weight = (spans / (full + noise[:, None, None, None])).clamp(0.0, 1.0).amax(0)
    else:
        weight = parallax.parallax_support(span, full)
    return weight, {'median_span_px': float(span.median()), 'mean_weight': float(weight.mean())}


def carry_support(predicted_logp_bdhw: Optional[torch.Tensor], weight: Optional[torch.Tensor], prev,
                  T_world_ref_44: np.ndarray, K_vol_b33: torch.Tensor, depths_d: torch.Tensor,
                  readout: str) -> Optional[torch.Tensor]:
    """Parallax support of the new posterior, (1, h, w) in [0, 1]: ``w + (1 - w) * s_pred``, where
    ``s_pred`` is the previous posterior's (``prev``: its support, pose and volume intrinsics) support carried into
    the reference with the predicted depth (0 where the previous keyframe did not see the pixel, and after a filter
    restart). It mirrors the filter's per-pixel blend of update and prediction, so a pixel keeps the support of the
    belief it carries; it multiplies the published confidence."""
    if weight is None:
        return None
    if predicted_logp_bdhw is None or prev is None or prev.support_bhw is None:
        return weight
    depth = dpv_ops.depth_estimate(predicted_logp_bdhw, depths_d, readout)
    T_prev_ref = np.linalg.inv(prev.T_world_cam_44) @ T_world_ref_44
    T_t = torch.as_tensor(T_prev_ref, dtype=torch.float32, device=depths_d.device)[None]
    s, ok = geometry.warp_image_with_depth(prev.support_bhw[:, None], depth, prev.K_vol_b33, K_vol_b33, T_t)
    s_pred = torch.where(ok, s[:, 0], torch.zeros_like(s[:, 0]))
    return weight + (1.0 - weight) * s_pred
