"""The estimator's configuration and the records it passes around: ``EstimatorConfig`` (from the settings table),
the output size rule, the pose refiner's request, and the filter's posterior and a measurement as the estimator
keeps them. torch and numpy only; no ROS."""
from __future__ import annotations

import pathlib
from dataclasses import dataclass
from typing import Any, Callable, List, Optional, Sequence, Tuple

import numpy as np
import torch

from dpv_sensor import params as P
from dpv_sensor.stream.keyframes import Keyframe

__all__ = ['EstimatorConfig', 'PoseRefinementRequest', 'PoseRefiner', 'default_weights_path', 'output_size']


def default_weights_path(preset: str) -> pathlib.Path:
    """The packaged checkpoint of a preset: ``<dpv_sensor package>/weights/<preset>.safetensors``
    (``nets.checkpoint.default_weights_path``; the file may not exist)."""
    from dpv_sensor.core.nets.checkpoint import default_weights_path as _default
    return _default(preset)


# ------------------------------------------------------------------------------------------------------
# configuration
# ------------------------------------------------------------------------------------------------------

def output_size(config, input_size) -> Tuple[int, int]:
    """(width, height) of the published maps for an input image of ``input_size`` (width, height): the input's
    with ``output_resolution='input'``; with ``'processing'`` processing_width wide with the input's aspect ratio
    (height rounded, at least 1), so the output pairs with the camera's colour images (depth_image_proc refuses
    a depth image whose aspect differs from the colour image's)."""
    in_w, in_h = int(input_size[0]), int(input_size[1])
    if config.output_resolution == 'input':
        return in_w, in_h
    w = int(config.processing_width)
    return w, max(1, int(round(w * in_h / in_w)))


def _processing_size(self) -> Tuple[int, int]:
    """(width, height) the images are resized to."""
    return int(self.processing_width), int(self.processing_height)


EstimatorConfig = P.make_config_class('EstimatorConfig', P.ESTIMATOR_SPECS, """Everything the estimator and its
pose source need: one field per ``estimator`` / ``library`` setting of the table in ``dpv_sensor.params``
(description, default, range and choices live there, once). :meth:`from_params` takes the fields from the
node's parameter dict (other keys are ignored); :meth:`validate` applies the table's checks, with the same
messages as the node and ``evaluate``. ``torch_threads`` > 0 is applied with ``torch.set_num_threads`` when the
Estimator is built (it is process-wide); 0 leaves torch's setting alone.""",
                                       {'processing_size': property(_processing_size)})
EstimatorConfig.__module__ = 'dpv_sensor.stream.estimator'


@dataclass
class PoseRefinementRequest:
    """What a pose refiner gets before the plane sweep of a window (paper eq. 11).

    keyframes: the window's keyframes in time order (reference included; ``Keyframe.T_world_cam_44`` is
    the current pose estimate, ``image_b3hw`` / ``K_b33`` the processing-size image and intrinsics).
    reference: index of the reference keyframe in ``keyframes``.
    depth_hw / confidence_hw: the depth and confidence the filter predicts for the reference (its last
    posterior warped into the reference pose); the confidence is always the +-1-plane mass
    (``dpv.confidence``, what ``photometric.inverse_depth_std_from_confidence`` expects), whatever the
    published ``confidence`` is; torch (h, w) at the volume resolution with intrinsics
    ``K_depth_33`` (numpy); None when the filter has no state yet (first window after a reset).
    The refiner returns a list of ``T_world_cam`` 4x4 arrays, one per keyframe (same order), or None.
    """
    keyframes: List[Keyframe]
    reference: int
    depth_hw: Optional[torch.Tensor]
    confidence_hw: Optional[torch.Tensor]
    K_depth_33: Optional[np.ndarray]
    depths_d: torch.Tensor


PoseRefiner = Callable[[PoseRefinementRequest], Optional[Sequence[np.ndarray]]]


@dataclass
class _Posterior:
    """The filter's latest posterior and where it lives (for between-keyframe outputs and prediction)."""
    logp_bdhw: torch.Tensor
    T_world_cam_44: np.ndarray
    K_vol_b33: torch.Tensor
    coverage_bhw: torch.Tensor          # bool, volume resolution
    stamp: float
    support_bhw: Optional[torch.Tensor] = None   # parallax support in [0, 1], volume resolution (None: rule off)
    median_depth: Optional[float] = None         # computed on demand (source scoring)


@dataclass
class _Measurement:
    logp_bdhw: torch.Tensor
    K_vol_b33: torch.Tensor
    feats: Any = None
