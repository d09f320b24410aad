"""The estimator's configuration and the records it passes around: ``EstimatorConfig`` (from the settings table),
the output size rule, the pose refiner's request, the status it reports (``EstimatorStatus``), and the filter's
posterior and a measurement as the estimator keeps them. torch and numpy only; no ROS."""
from __future__ import annotations

import dataclasses
import pathlib
from dataclasses import dataclass
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch

from dpv_sensor import params as P
from dpv_sensor.stream.keyframes import Keyframe

__all__ = ['EstimatorConfig', 'EstimatorStatus', 'PoseRefinementRequest', 'PoseRefiner', 'default_weights_path',
           'output_size', 'calibration_signature']


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
class EstimatorStatus:
    """What the estimator reports (``Estimator.status``, and ``Pipeline.status`` with the pose source's tracking):
    the measurement model in use and why, device and precision, the settings in force, counters, resets, the
    tracking state. :meth:`as_dict` is its JSON form (``summary.json``, ``fuse``)."""
    measurement: str                            # 'network' or 'classical'
    measurement_reason: str                     # why that model (weights loaded from, classical fallback ...)
    preset: Optional[str]                       # the network's preset, None with the classical model
    weights: Optional[str]                      # the checkpoint loaded, None when none was
    checkpoint: Optional[Dict[str, Any]]        # preset, steps, training_data, code_version of the checkpoint
    device: str
    precision: str                              # what the networks run in
    inference_backend: str                      # what runs them (inference_backend, 'torch' after a fallback)
    torch_threads: int
    filter_mode: str                            # in use (knet falls back to global without the network)
    filter_mode_requested: str
    depth_readout: str                          # 'auto' resolved
    confidence: str                             # 'plane' or 'ratio <r>'
    window_mode: str
    processing_size: Tuple[int, int]            # (width, height)
    depth_range: Tuple[float, float]            # (d_min, d_max) of the depth planes in metres
    num_planes: int
    frames: int                                 # pushed
    frames_accepted: int
    frames_dropped: int
    keyframes: int
    keyframes_in_window: int
    outputs: int
    resets: int
    pose_refinement_fallbacks: int
    last_pose_refinement_fallback_reason: Optional[str]
    last_reset_reason: Optional[str]
    last_drop_reason: Optional[str]
    frames_degenerate: int
    last_degenerate_reason: Optional[str]
    parallax: Dict[str, float]                  # the parallax rule's figures of the last window
    pose_uncertainty: Dict[str, Any]            # source and size of the last window's pose uncertainty ({}: none)
    tracking: str
    pose_refinement: str
    pose_refiner: bool                          # a pose refiner is in use
    last_timings_ms: Dict[str, float]
    notes: List[str]                            # one-time warnings
    pose_refinement_tracking: Optional[str] = None   # the pose source's (Pipeline.status); None without a refiner
    # the window refiner's gate: windows per outcome (refined, kept_few_inliers, rejected_chi2, skipped, lost, none)
    # and the last window's largest step correction (m, deg); empty / zeros without a refiner that reports them
    pose_refinement_gate: Dict[str, int] = dataclasses.field(default_factory=dict)
    pose_refinement_factors: Dict[str, int] = dataclasses.field(default_factory=dict)
    pose_refinement_correction: Tuple[float, float] = (0.0, 0.0)
    # the last window's odometry factors: (median per-axis std of a step: rotation rad, translation m; where their
    # covariance came from: fixed sigmas, published covariance, drift figures); None without them
    pose_refinement_odometry: Optional[Tuple[float, float, str]] = None
    # the median over the window refiner's last flow pairs of their direction ratio and the threshold below which
    # rotation_evidence 'auto' takes the flow (core.flow_rotation); None before a pair has one or without the flow
    pose_refinement_direction_ratio: Optional[Tuple[float, float]] = None
    # the confidence calibration file in use (the confidence_calibration setting), None without one
    confidence_calibration: Optional[str] = None
    # the metric anchors since the start (stream.metric_anchors.AnchorStatus as a dict): mode, keyframes checked,
    # aligned and overruled, anchors kept and rejected by reason, the last keyframe's report
    anchors: Dict[str, Any] = dataclasses.field(default_factory=dict)
    # the mount check (stream.mount_check.MountCheckStatus as a dict: pairs, fits, the last fit, whether the mount
    # or the stamps are confidently off); empty without one
    mount_check: Dict[str, Any] = dataclasses.field(default_factory=dict)

    def as_dict(self) -> Dict[str, Any]:
        """The fields by name (``dataclasses.asdict``); ``pose_refinement_tracking`` only when there is one."""
        out = dataclasses.asdict(self)
        if out['pose_refinement_tracking'] is None:
            del out['pose_refinement_tracking']
        return out


def calibration_signature(status: EstimatorStatus) -> Dict[str, Any]:
    """The estimator settings a confidence calibration map depends on (``core.confidence_calibration.signature``),
    from a status: what the calibrate tool writes into a map and what the estimator checks a map against."""
    from dpv_sensor.core.confidence_calibration import signature
    return signature(status.measurement, status.weights, status.processing_size, status.depth_range,
                     status.num_planes, status.confidence)


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
