"""The pose uncertainty of a keyframe window, as the estimator applies it (docs/estimator.md, the pose-uncertainty
step): which frames' odometry covariances (pose and twist) it reads, the drift figures of ``pose_uncertainty``, each
source's std relative to the reference as a std in planes of the measured plane index (the window refiner's marginals
where it solved the window), and the share of the ratio confidence that survives it. The maths is
:mod:`dpv_sensor.core.pose_uncertainty`; this module only maps the estimator's settings onto it. No ROS import.
"""
from __future__ import annotations

from typing import Dict, List, Optional, Tuple

import numpy as np
import torch

from dpv_sensor.core import pose_uncertainty

__all__ = ['frame_covariance', 'drift_model', 'window_sigma_planes', 'confidence_factor']


def frame_covariance(cfg, frame, which: str = 'pose') -> Optional[np.ndarray]:
    """The frame's odometry covariance (6x6; ``which``: 'pose' or 'twist') when ``cfg.pose_uncertainty`` reads it
    (covariance, auto) and the frame has one."""
    cov = getattr(frame, f'{which}_covariance_66', None)
    if cov is None or cfg.pose_uncertainty not in ('covariance', 'auto'):
        return None
    cov = np.asarray(cov, np.float64)
    return cov.reshape(6, 6) if cov.size == 36 else None


def drift_model(cfg) -> pose_uncertainty.DriftModel:
    """The drift figures of the settings (all zero with ``pose_uncertainty: covariance``: only the odometry's
    covariance, its translation capped by ``odom_drift_trans`` per metre either way)."""
    if cfg.pose_uncertainty == 'covariance':
        return pose_uncertainty.DriftModel(0.0, 0.0, 0.0, 0.0, cov_trans_per_m=cfg.odom_drift_trans)
    return pose_uncertainty.DriftModel(trans_per_m=cfg.odom_drift_trans, rot_deg_per_m=cfg.odom_drift_rot_deg_per_m,
                                       rot_per_deg=cfg.odom_drift_rot, sync_s=cfg.odom_time_sync_ms / 1000.0,
                                       cov_trans_per_m=cfg.odom_drift_trans)


def window_sigma_planes(cfg, geom, ref, sources: List, K_vol_b33: torch.Tensor, plane_step_rho: float,
                        marginals: Optional[Dict[float, pose_uncertainty.PoseSigma]] = None
                        ) -> Tuple[Optional[torch.Tensor], Dict[str, float]]:
    """(1, h, w) std (planes, volume resolution) of the measured plane index that the sources' pose uncertainty
    relative to the reference causes, and its status (where it came from and its size); None with
    ``pose_uncertainty`` off, without the sweep geometry ``geom`` (depth, spans), or with ``covariance`` and no
    covariance. marginals: a pose refiner's per-source std by stamp, used in place of the odometry's."""
    mode = cfg.pose_uncertainty
    if mode == 'off' or geom is None:
        return None, {}
    depth, spans = geom
    return pose_uncertainty.window_sigma_planes(ref, sources, depth, spans, K_vol_b33, drift_model(cfg),
                                                plane_step_rho, covariance_only=mode == 'covariance',
                                                source_sigma=marginals or None)


def confidence_factor(cfg, post_bdhw: torch.Tensor, sigma_planes_bhw: torch.Tensor, depths_d: torch.Tensor,
                      readout: str) -> torch.Tensor:
    """(1, h, w) in [0, 1]: the share of the belief's ratio confidence that survives the pose uncertainty (1
    everywhere for the ``plane`` confidence)."""
    if cfg.confidence != 'ratio':
        return torch.ones_like(sigma_planes_bhw)
    return pose_uncertainty.confidence_factor(post_bdhw, depths_d, readout, cfg.confidence_ratio, sigma_planes_bhw)
