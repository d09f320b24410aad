"""From the estimator's maps to a published :class:`~dpv_sensor.stream.frame.DepthOutput`: volume-resolution maps
brought to the processing size, and the output composed (masks, ``min_confidence``, the output size with nearest
resampling, the intrinsics of that size). torch and numpy only; no ROS."""
from __future__ import annotations

import numpy as np
import torch

from dpv_sensor.stream.estimator_config import output_size
from dpv_sensor.stream.frame import DepthOutput
from dpv_sensor.core.geometry import resample_to_camera
from dpv_sensor.core.pose_math import scale_intrinsics_np

__all__ = ['volume_maps_to_processing', 'compose_output']


def volume_maps_to_processing(depth_bhw, conf_bhw, valid_bhw, K_vol_33, K_proc_33, hw):
    """Volume-resolution depth/confidence/validity -> processing size (inverse depth bilinear)."""
    inv = 1.0 / depth_bhw.clamp_min(1e-6)
    maps = torch.stack([inv, conf_bhw], 1)
    up = resample_to_camera(maps, K_vol_33, K_proc_33, hw, mode='bilinear')
    valid = resample_to_camera(valid_bhw[:, None].float(), K_vol_33, K_proc_33, hw, mode='nearest')[:, 0] > 0.5
    return 1.0 / up[:, 0].clamp_min(1e-6), up[:, 1], valid


def compose_output(config, depth_bhw, conf_bhw, valid_bhw, input_size, K_in_33, stamp, T_world_cam, is_keyframe,
                   reset_reason, calibration=None) -> DepthOutput:
    """Mask, calibrate the confidence, resize to the output size (nearest) and convert to numpy float32.

    Pixels without an estimate get NaN depth and confidence 0. ``calibration`` (a
    ``core.confidence_calibration.ConfidenceCalibration``, the ``confidence_calibration`` setting) maps the confidence
    of the pixels with an estimate; the depth does not depend on it. With ``config.min_confidence`` > 0, depth whose
    (calibrated) confidence is below it is NaN too (no estimate), while its confidence is kept."""
    valid = valid_bhw & torch.isfinite(depth_bhw) & (depth_bhw > 0)
    conf = conf_bhw.clamp(0.0, 1.0)
    if calibration is not None:
        conf = calibration.apply(conf)
    conf = torch.where(valid, conf, torch.zeros_like(conf_bhw))
    if config.min_confidence > 0.0:
        valid = valid & (conf >= config.min_confidence)
    depth = torch.where(valid, depth_bhw, torch.full_like(depth_bhw, float('nan')))
    H, W = depth.shape[-2:]
    # the processing K in float64, exactly as the resize convention gives it
    K_out = scale_intrinsics_np(K_in_33, W / input_size[0], H / input_size[1])
    out_w, out_h = output_size(config, input_size)
    if (out_w, out_h) != (W, H):
        K_target = np.array(K_in_33, dtype=np.float64, copy=True) if (out_w, out_h) == tuple(input_size[:2]) \
            else scale_intrinsics_np(K_in_33, out_w / input_size[0], out_h / input_size[1])
        maps = torch.stack([depth, conf], 1)
        maps = resample_to_camera(maps, K_out, K_target, (out_h, out_w), mode='nearest')
        depth, conf = maps[:, 0], maps[:, 1]
        K_out = K_target
    return DepthOutput(stamp=float(stamp),
                       depth_hw=depth[0].float().cpu().numpy(),
                       confidence_hw=conf[0].float().cpu().numpy(),
                       K_33=K_out, is_keyframe=is_keyframe,
                       T_world_cam_44=np.array(T_world_cam, dtype=np.float64, copy=True),
                       reset_reason=reset_reason)
