"""The confidence cues of one keyframe as the estimator has them (``dpv_sensor.core.confidence_features`` holds the
maths): every cue brought to the processing size, as float32 numpy maps keyed by name. The estimator gathers them
only when asked (``Estimator.collect_features``: the confidence study and a feature calibration map); the published
depth and confidence do not depend on them. No ROS import.

Cues (``FEATURES``): ``band_mass`` (the DPV's mass in the x1.25 band, before the pose and parallax factors),
``confidence`` (the raw published confidence), ``entropy``, ``second_mode``, ``parallax_px`` (the widest disparity
span over the sources of the band around the measurement's depth, processing pixels), ``parallax_weight`` and
``support`` (the parallax rule's weight of this measurement and of the belief; 1 when the rule is off),
``pose_sigma`` (the pose uncertainty's std in planes; 0 when none), ``photometric`` and ``views`` (the sources'
colour residual at the published depth and how many sources see the pixel), ``texture`` and ``innovation`` (planes
between the measurement and the prediction; NaN on the first keyframe of a belief).
"""
from __future__ import annotations

from typing import Dict, Optional, Sequence

import numpy as np
import torch

from dpv_sensor.core import confidence_features as C
from dpv_sensor.core.geometry import resample_to_camera

__all__ = ['FEATURES', 'keyframe_features']

FEATURES = ('band_mass', 'confidence', 'entropy', 'second_mode', 'parallax_px', 'parallax_weight', 'support',
            'pose_sigma', 'photometric', 'views', 'texture', 'innovation')


def _numpy(x_bhw: torch.Tensor) -> np.ndarray:
    return x_bhw[0].detach().float().cpu().numpy()


def keyframe_features(*, full_logp_bdhw: torch.Tensor, depth_bhw: torch.Tensor, band_mass_bhw: torch.Tensor,
                      conf_bhw: torch.Tensor, depths_d: torch.Tensor, ratio: float, readout: str,
                      ref_image_b3hw: torch.Tensor, src_images: Sequence[torch.Tensor], K_proc_b33: torch.Tensor,
                      T_src_ref_n44: torch.Tensor, K_vol_33: torch.Tensor, measured_logp_bdhw: torch.Tensor,
                      predicted_logp_bdhw: Optional[torch.Tensor], spans_n1hw: Optional[torch.Tensor],
                      weight_bhw: Optional[torch.Tensor], support_bhw: Optional[torch.Tensor],
                      sigma_planes_bhw: Optional[torch.Tensor]) -> Dict[str, np.ndarray]:
    """The cues of one keyframe (:data:`FEATURES`), each (H, W) float32 at the processing size (volume-resolution
    cues resampled bilinearly, as the confidence is)."""
    H, W = depth_bhw.shape[-2:]
    K_proc = K_proc_b33[0]

    def up(x_bhw: Optional[torch.Tensor], fill: float) -> torch.Tensor:
        if x_bhw is None:
            return torch.full((1, H, W), fill, device=depth_bhw.device)
        return resample_to_camera(x_bhw.float()[:, None], K_vol_33, K_proc, (H, W))[:, 0]

    srcs = torch.cat([s for s in src_images], 0) if len(src_images) else ref_image_b3hw[:0]
    residual, views = C.photometric_residual(ref_image_b3hw, srcs, depth_bhw, K_proc_b33, T_src_ref_n44)
    out = {
        'band_mass': band_mass_bhw,
        'confidence': conf_bhw,
        'entropy': C.entropy_share(full_logp_bdhw),
        'second_mode': C.second_mode_mass(full_logp_bdhw, depths_d, depth_bhw, ratio),
        'parallax_px': up(None if spans_n1hw is None else spans_n1hw.amax(0), float('nan')),
        'parallax_weight': up(weight_bhw, 1.0),
        'support': up(support_bhw, 1.0),
        'pose_sigma': up(sigma_planes_bhw, 0.0),
        'photometric': residual,
        'views': views,
        'texture': C.image_texture(ref_image_b3hw),
        'innovation': up(C.innovation_planes(measured_logp_bdhw, predicted_logp_bdhw, depths_d, readout), float('nan')),
    }
    return {k: _numpy(out[k]) for k in FEATURES}
