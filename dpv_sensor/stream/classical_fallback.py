"""The classical plane sweep's depth of one keyframe, computed only where the anchors overrule the networks (layer 3).

The networks learnt their depth prior on rendered rooms; on a real image whose matching evidence is weak (a desk
close to the camera, a texture the renders never had) the prior speaks and the depth can be far off, while the
training-free NCC plane sweep (:class:`~dpv_sensor.core.classical.ClassicalMeasurement`) only says what the images
match. With ``anchor_fallback: classical``, when a keyframe's metric anchors overrule the networks' depth in some
region (:class:`~dpv_sensor.stream.metric_anchors.AnchorAligner`), the aligner asks for a second opinion: this
sweep over the same reference and sources, with the same poses, read out as ``depth_readout: auto`` reads the
classical model (``mean`` over the planes) with the configured confidence, at the processing size. The aligner holds
it to the same anchors and blends it in, only in the overruled pixels. Its confidence carries neither the
pose-uncertainty factor nor the filter's temporal support that the networks' has: where the pose is uncertain the
blend leans towards the sweep more than it would with both. Nothing is computed on a keyframe the anchors do not
overrule, nor when the measurement is already the sweep. torch and numpy; no ROS.
"""
from __future__ import annotations

import time
from typing import Callable, Dict, Optional, Sequence, Tuple

import numpy as np
import torch

from dpv_sensor.core import dpv as dpv_ops
from dpv_sensor.core.classical import ClassicalMeasurement
from dpv_sensor.core.geometry import resample_to_camera

__all__ = ['ClassicalFallback']

#: the classical model's depth readout (the estimator's ``auto`` picks it for the sweep)
READOUT = 'mean'


class ClassicalFallback:
    """Builds the sweep once (over the depth planes of the estimator's measurement, ``depth_range`` and
    ``num_planes``, at ``classical_downscale``) and hands the aligner a callable per keyframe that computes that
    keyframe's classical (depth, confidence) when called."""

    def __init__(self, config, depth_range, num_planes: int, device=None):
        self.config = config
        self.sweep = ClassicalMeasurement(depth_range[0], depth_range[1], num_planes,
                                          downscale=config.classical_downscale)
        self.depths_d = self.sweep.depths(torch.float32, device)

    @classmethod
    def for_config(cls, config, measurement: str, depth_range, num_planes: int, device=None
                   ) -> Optional['ClassicalFallback']:
        """The fallback an estimator needs: None unless ``anchor_fallback`` is 'classical', the anchors are on and
        the measurement is the networks (the sweep gives no second opinion on itself)."""
        if config.anchor_fallback != 'classical' or config.depth_anchors == 'off' or measurement != 'network':
            return None
        return cls(config, depth_range, num_planes, device)

    def opinion(self, ref, sources: Sequence, T_src_ref_b_n44: torch.Tensor,
                timings: Optional[Dict[str, float]] = None) -> Callable[[], Optional[Tuple[np.ndarray, np.ndarray]]]:
        """A callable giving the reference keyframe's classical (depth, confidence) from its ``sources``
        (:class:`~dpv_sensor.stream.keyframes.Keyframe`), float32 arrays at the reference image's size (NaN depth
        where no source sees the pixel); its time goes to ``timings['anchors.classical']``."""
        ref_b3hw, K_b33 = ref.image_b3hw, ref.K_b33
        src_images = [s.image_b3hw for s in sources]

        def compute() -> Optional[Tuple[np.ndarray, np.ndarray]]:
            if not src_images:
                return None
            t = time.perf_counter()
            with torch.no_grad():
                srcs = torch.stack([s[0] for s in src_images])[None].float()
                logp, count, K_vol = self.sweep.measure_with_views(ref_b3hw.float(), srcs, K_b33.float(),
                                                                   T_src_ref_b_n44.float())
                depth = dpv_ops.depth_estimate(logp, self.depths_d, READOUT)
                conf = dpv_ops.published_confidence(logp, self.depths_d, depth, self.config.confidence,
                                                    self.config.confidence_ratio)
                seen = (count > 0).any(1).float()
                H, W = ref_b3hw.shape[-2:]
                maps = torch.stack([1.0 / depth.clamp_min(1e-6), conf, seen], 1)
                up = resample_to_camera(maps, K_vol[0], K_b33[0], (H, W), mode='bilinear')[0]
            inv, c, s = (m.cpu().numpy() for m in up)
            out = np.where(s > 0.5, 1.0 / np.maximum(inv, 1e-6), np.nan).astype(np.float32)
            if timings is not None:
                timings['anchors.classical'] = (time.perf_counter() - t) * 1000.0
            return out, np.where(s > 0.5, c, 0.0).astype(np.float32)
        return compute
