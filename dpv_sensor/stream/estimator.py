"""The streaming core of the virtual depth camera: ``Estimator(config).push(Frame) -> DepthOutput | None``.

No ROS import here; the node only converts messages to :class:`Frame` and :class:`DepthOutput` back to messages.
What happens to a pushed frame, step by step (checks and resets, keyframes, the window, pose refinement, the
measurement, the filter, the parallax rule, the pose uncertainty, the outputs, degenerate frames, device and
precision), is written out in docs/estimator.md; the items there are numbered as referred to below.
"""
from __future__ import annotations

import logging
import math
import pathlib
import time
from typing import Any, Dict, List, Optional, Tuple

import cv2
import numpy as np
import torch

from dpv_sensor import params as P
from dpv_sensor.core import confidence_calibration, dpv as dpv_ops, geometry, image_quality, parallax, pose_uncertainty
from dpv_sensor.core.confidence_calibration import ConfidenceCalibration
from dpv_sensor.core.edge_filter import joint_weighted_median
from dpv_sensor.core.geometry import resample_to_camera, subsampled_intrinsics
from dpv_sensor.core.pose_math import scale_intrinsics_np
from dpv_sensor.core.keypoint_pose import to_gray_u8
from dpv_sensor.core.nets.model import cpu_bf16_fast
from dpv_sensor.stream.continuity import DUPLICATE, stream_break, time_order
from dpv_sensor.stream.frame import DepthOutput, Frame, checked_image, drop_reason, is_rigid
from dpv_sensor.stream.depth_output import compose_output, volume_maps_to_processing
from dpv_sensor.stream.estimator_config import (EstimatorConfig, EstimatorStatus, PoseRefinementRequest,  # noqa: F401
                                                PoseRefiner, _Measurement, _Posterior, calibration_signature,
                                                default_weights_path, output_size)
from dpv_sensor.stream.keyframes import Keyframe, KeyframeSelector, KeyframeWindow
from dpv_sensor.stream import (classical_fallback, confidence_features, keyframe_geometry, metric_anchors,
                               window_pose_uncertainty)

__all__ = ['EstimatorConfig', 'EstimatorStatus', 'Estimator', 'PoseRefinementRequest', 'default_weights_path',
           'MEASUREMENTS', 'FILTER_MODES']

LOG = logging.getLogger('dpv_sensor.stream.estimator')

MEASUREMENTS = P.choices('measurement')
FILTER_MODES = P.choices('filter_mode')
OUTPUT_RESOLUTIONS = P.choices('output_resolution')
CPU_PRECISIONS = P.choices('cpu_precision')


# ------------------------------------------------------------------------------------------------------
# small helpers
# ------------------------------------------------------------------------------------------------------

def _odometry_steps(result) -> Optional[Tuple[float, float, str]]:
    """A refiner result's odometry factors (``RefinementResult.odometry``) as the status holds them."""
    steps = getattr(result, 'odometry', None)
    return None if steps is None else (float(steps[0]), float(steps[1]), str(steps[2]))


# ------------------------------------------------------------------------------------------------------
# the estimator
# ------------------------------------------------------------------------------------------------------

class Estimator:
    """Streaming depth estimation from posed frames (see docs/estimator.md).

    Args:
        config: an :class:`EstimatorConfig` (``EstimatorConfig.from_params(params.validate(...))`` in the
            node).
        model: an already built ``DPVNet`` to use as the measurement model (e.g. random-init weights for
            benchmarks, a model just trained); skips checkpoint loading. Ignored with
            ``measurement='classical'``.
        pose_refiner: optional callable ``(PoseRefinementRequest) -> list of T_world_cam | None``, called
            before every plane sweep. The node builds one when ``pose_refinement='window'``.
        logger: a ``logging.Logger``-like object (``warning``/``info``); default ``dpv_sensor.stream.estimator``.
    """

    def __init__(self, config: Optional[EstimatorConfig] = None, *, model=None,
                 pose_refiner: Optional[PoseRefiner] = None, logger=None):
        self.config = (config or EstimatorConfig()).validate()
        self.log = logger or LOG
        cfg = self.config
        self.device = self._resolve_device(cfg.device)
        if cfg.torch_threads > 0 and torch.get_num_threads() != cfg.torch_threads:
            torch.set_num_threads(int(cfg.torch_threads))
        self.pose_refiner = pose_refiner
        self._notes: List[str] = []
        self.model = None
        self.nets = None                   # where the networks run (core.nets.runtime), with the network
        self.classical = None
        self._weights_path: Optional[str] = None
        self._checkpoint_meta: Dict[str, Any] = {}
        self._build_measurement(model)
        self._build_filter()
        self.anchors = metric_anchors.AnchorAligner(cfg.depth_anchors, ratio=cfg.confidence_ratio,
                                                    depth_range=(self.d_min, self.d_max), judge=cfg.anchor_judge)
        if cfg.depth_anchors != 'off' and cfg.pose_refinement != 'window':
            self._note(metric_anchors.NEEDS_WINDOW.format(mode=cfg.depth_anchors))
        self.fallback = classical_fallback.ClassicalFallback.for_config(cfg, self.measurement, (self.d_min, self.d_max),
                                                                        self.num_planes, self.device)
        if cfg.pose_refinement == 'window' and pose_refiner is None:
            self._note('pose_refinement=window requested but no pose refiner was given: poses are used as received')
        if cfg.cpu_precision == 'bfloat16' and self.device.type == 'cpu' and self.model is not None \
                and not cpu_bf16_fast():
            self._note('cpu_precision=bfloat16: this CPU has no native bfloat16 kernels (AMX / AVX512-BF16), so '
                       'the networks run emulated bfloat16, slower than float32')
        if cfg.publish_between_keyframes and cfg.window_mode == 'centered':
            self._note('publish_between_keyframes is ignored in centered window mode (its outputs would be '
                       'newer than the pending keyframe outputs)')
        self.selector = KeyframeSelector(cfg.keyframe_translation, cfg.keyframe_rotation_deg,
                                         cfg.keyframe_max_interval)
        self.window = KeyframeWindow(cfg.window_size, pool=cfg.source_pool)
        # counters and stream state
        self._frames_received = 0
        self._frames_accepted = 0
        self._frames_dropped = 0
        self._keyframes = 0
        self._outputs = 0
        self._resets = 0
        self._refine_fallbacks = 0
        self._last_refine_fallback_reason: Optional[str] = None
        self._last_reset_reason: Optional[str] = None
        self._last_drop_reason: Optional[str] = None
        self._pending_reset_reason: Optional[str] = None
        self._last_frame: Optional[Tuple[float, np.ndarray, Tuple[int, int], np.ndarray]] = None
        self._posterior: Optional[_Posterior] = None
        self._anchor_T_world: Optional[np.ndarray] = None
        self._tracking = 'waiting for frames'
        self._last_timings: Dict[str, float] = {}
        self._knet_ms = 0.0                # K-Net's share of the filter step being timed
        self._kf_counter = 0
        self._frames_degenerate = 0
        self._last_degenerate_reason: Optional[str] = None
        self.last_image_quality: Optional[image_quality.ImageQuality] = None
        self._last_parallax: Dict[str, float] = {}
        self._last_pose_sigma: Dict[str, float] = {}
        self._twist: Optional[np.ndarray] = None
        self.calibration: Optional[ConfidenceCalibration] = None
        self.calibration = self._load_calibration()
        # keyframe outputs carry their confidence cues (stream.confidence_features) when set, with the network
        # measurement only; off for the node
        self.collect_features = False

    # ------------------------------------------------------------------ construction helpers
    @staticmethod
    def _resolve_device(name: str) -> torch.device:
        try:
            dev = torch.device(name)
        except (RuntimeError, TypeError) as exc:
            raise ValueError(f'device {name!r} is not a torch device: {exc}') from None
        if dev.type == 'cuda':
            if not torch.cuda.is_available():
                raise ValueError(f'device {name!r} requested but CUDA is not available on this machine')
            if dev.index is not None and dev.index >= torch.cuda.device_count():
                raise ValueError(f'device {name!r} requested but only {torch.cuda.device_count()} CUDA devices exist')
        elif dev.type != 'cpu':
            raise ValueError(f'device {name!r}: only cpu and cuda are supported')
        return dev

    def _note(self, text: str) -> None:
        """Log a one-time warning and keep it for the status."""
        if text not in self._notes:
            self._notes.append(text)
            self.log.warning(text)

    def _build_measurement(self, model) -> None:
        cfg = self.config
        if cfg.measurement == 'classical':
            self._use_classical('measurement=classical')
            return
        if model is not None:
            self.model = model.to(self.device).eval()
            self._measurement_reason = f'network ({self.model.preset.name}) passed in by the caller'
            self._use_network()
            return
        path = pathlib.Path(cfg.weights) if cfg.weights else default_weights_path(cfg.preset)
        try:
            self.model = self._load_network(path)
        except Exception as exc:  # CheckpointError, or the checkpoint module itself missing
            reason = f'no network weights for preset {cfg.preset!r}: {type(exc).__name__}: {exc}'
            if cfg.measurement == 'network':
                raise
            self.log.warning(f'{reason}; falling back to the classical (NCC plane sweep) measurement model')
            self._use_classical(f'fallback: {reason}')
            return
        self._weights_path = str(path)
        self._measurement_reason = f'network weights loaded from {path}'
        self._use_network()

    def _load_calibration(self) -> Optional[ConfidenceCalibration]:
        """The confidence calibration map of the ``confidence_calibration`` setting (None when empty), checked
        against this estimator (weights, processing size, depth planes, confidence); a file that is malformed or was
        fitted for other settings raises ParameterError naming the setting."""
        path = self.config.confidence_calibration
        if not path:
            return None
        try:
            calibration = confidence_calibration.load(path)
            calibration.check_signature(calibration_signature(self.status))
        except confidence_calibration.CalibrationError as exc:
            raise P.ParameterError(f"parameter 'confidence_calibration' = {path!r} refused: {exc}") from None
        self.log.info(f'confidence calibration {path}: {len(calibration.confidence)} knots, fitted on '
                      f"{calibration.fitted_on.get('source', 'an unnamed source')}")
        return calibration

    def _load_network(self, path: pathlib.Path):
        """DPVNet from a checkpoint; raises CheckpointError (file missing, corrupt, other preset ...)."""
        from dpv_sensor.core.nets.checkpoint import load_checkpoint
        model, meta = load_checkpoint(str(path), preset=self.config.preset, device=self.device,
                                      processing_size=(self.config.processing_width, self.config.processing_height))
        self._checkpoint_meta = dict(meta or {})
        return model.to(self.device).eval()

    @property
    def readout(self) -> str:
        """The depth readout in use (``depth_readout`` with 'auto' resolved for the measurement model)."""
        return dpv_ops.resolve_readout(self.config.depth_readout, self.measurement == 'network')

    def _use_network(self) -> None:
        from dpv_sensor.core.nets.runtime import build_runner
        self.measurement = 'network'
        m = self.model
        self.depths_d = m.depth_planes(torch.float32, self.device)
        self.d_min, self.d_max, self.num_planes = float(m.d_min), float(m.d_max), int(m.num_planes)
        W, H = self.config.processing_size
        self.nets = build_runner(m, self.config.inference_backend, (H, W), self.device, bfloat16=self._cpu_bfloat16(),
                                 autocast=self._autocast, note=self._note)

    def _use_classical(self, reason: str) -> None:
        from dpv_sensor.core.classical import ClassicalMeasurement
        cfg = self.config
        self.measurement = 'classical'
        self._measurement_reason = reason
        self.model = None
        self.nets = None
        self.classical = ClassicalMeasurement(cfg.d_min, cfg.d_max, cfg.num_planes,
                                              downscale=cfg.classical_downscale)
        self.depths_d = dpv_ops.depth_planes(cfg.d_min, cfg.d_max, cfg.num_planes, torch.float32, self.device)
        self.d_min, self.d_max, self.num_planes = float(cfg.d_min), float(cfg.d_max), int(cfg.num_planes)

    def _build_filter(self) -> None:
        from dpv_sensor.core.filter import DPVFilter
        cfg = self.config
        mode = cfg.filter_mode
        knet = None
        if mode == 'knet':
            if self.measurement == 'network':
                knet = self._knet_callable()
            else:
                mode = 'global'
                self._note('filter_mode=knet needs the network (K-Net); using global damping with the '
                           'classical measurement model')
        self.filter_mode = mode
        # The filter steps at keyframes only: time and motion between keyframes say nothing about the stream's
        # continuity (every pushed frame is checked in push, by the stream rules and the teleport rule, and a
        # discontinuity resets the filter there), so the filter's own time-gap and jump rules are off.
        self.filter = DPVFilter(mode=mode, damping=cfg.damping, knet=knet, max_time_gap=math.inf,
                                max_translation=math.inf, max_rotation_deg=math.inf)

    def _cpu_bfloat16(self) -> bool:
        p = self.config.cpu_precision
        return self.device.type == 'cpu' and (p == 'bfloat16' or (p == 'auto' and cpu_bf16_fast()))

    def _precision(self) -> str:
        """What the networks run in (the geometry, filter and DPV normalisations are always float32)."""
        if self.model is None:
            return 'float32'
        if self.nets.backend != 'torch':
            return f'{self.nets.runtime.precision} ({self.nets.backend})'
        if self.device.type == 'cuda' and self.config.amp_dtype != 'none':
            return f'{self.config.amp_dtype} autocast'
        if self._cpu_bfloat16():
            return 'bfloat16 autocast' + ('' if cpu_bf16_fast() else ' (emulated: no AMX / AVX512-BF16)')
        return 'float32'

    def _autocast(self):
        if self.device.type == 'cuda' and self.config.amp_dtype != 'none':
            return torch.autocast('cuda', dtype=getattr(torch, self.config.amp_dtype))
        if self._cpu_bfloat16():
            return torch.autocast('cpu', dtype=torch.bfloat16)
        return torch.autocast(self.device.type, enabled=False)

    def _knet_callable(self):
        def g(residual_bdhw, image_b3hw):
            t = time.perf_counter()
            out = self.nets.knet(residual_bdhw, image_b3hw)
            self._knet_ms += self._ms(t)
            return out
        return g

    # ------------------------------------------------------------------ public API
    @property
    def counts(self) -> Tuple[int, int]:
        """(keyframes, degenerate frames) so far: what a caller compares around one push, without the status."""
        return self._keyframes, self._frames_degenerate

    @property
    def status(self) -> EstimatorStatus:
        """Diagnostics: measurement model in use and why, device, counters, resets, tracking state."""
        cfg = self.config
        return EstimatorStatus(
            measurement=self.measurement,
            measurement_reason=self._measurement_reason,
            preset=self.model.preset.name if self.model is not None else None,
            weights=self._weights_path,
            checkpoint={k: self._checkpoint_meta.get(k) for k in ('preset', 'steps', 'training_data', 'code_version')}
            if self._checkpoint_meta else None,
            device=str(self.device),
            precision=self._precision(),
            inference_backend=self.nets.backend if self.nets is not None else 'torch',
            torch_threads=torch.get_num_threads(),
            filter_mode=self.filter_mode,
            filter_mode_requested=cfg.filter_mode,
            depth_readout=self.readout,
            confidence=cfg.confidence if cfg.confidence == 'plane' else f'ratio {cfg.confidence_ratio:g}',
            window_mode=cfg.window_mode,
            processing_size=cfg.processing_size,
            depth_range=(self.d_min, self.d_max),
            num_planes=self.num_planes,
            frames=self._frames_received,
            frames_accepted=self._frames_accepted,
            frames_dropped=self._frames_dropped,
            keyframes=self._keyframes,
            keyframes_in_window=len(self.window),
            outputs=self._outputs,
            resets=self._resets,
            pose_refinement_fallbacks=self._refine_fallbacks,
            last_pose_refinement_fallback_reason=self._last_refine_fallback_reason,
            last_reset_reason=self._last_reset_reason,
            last_drop_reason=self._last_drop_reason,
            frames_degenerate=self._frames_degenerate,
            last_degenerate_reason=self._last_degenerate_reason,
            parallax=dict(self._last_parallax),
            pose_uncertainty=dict(self._last_pose_sigma),
            tracking=self._tracking,
            pose_refinement=cfg.pose_refinement,
            pose_refiner=self.pose_refiner is not None,
            last_timings_ms=dict(self._last_timings),
            notes=list(self._notes),
            pose_refinement_gate=dict(getattr(self.pose_refiner, 'gate_counts', None) or {}),
            pose_refinement_factors=dict(getattr(self.pose_refiner, 'factor_counts', None) or {}),
            pose_refinement_correction=tuple(getattr(self._refinement_result(), 'correction', (0.0, 0.0))),
            pose_refinement_odometry=_odometry_steps(self._refinement_result()),
            pose_refinement_direction_ratio=getattr(self.pose_refiner, 'direction_ratio', None),
            confidence_calibration=None if self.calibration is None else self.calibration.path,
            anchors=self.anchors.status.as_dict(),
        )

    def _refinement_result(self):
        """The pose refiner's result of the last window it solved (None without a refiner that keeps one)."""
        return getattr(self.pose_refiner, 'last_result', None)

    def reset(self, reason: str = 'reset requested') -> None:
        """Forget the window, the keyframe selector and the filter state (counters are kept)."""
        self.window.clear()
        self.selector.reset()
        self.filter.reset()
        self._posterior = None
        self._anchor_T_world = None
        self._last_frame = None
        if self.pose_refiner is not None and callable(getattr(self.pose_refiner, 'reset', None)):
            self.pose_refiner.reset()
        self._resets += 1
        self._last_reset_reason = reason
        self._pending_reset_reason = reason
        self._tracking = 'waiting for keyframes'
        self.log.info(f'estimator reset: {reason}')

    def push(self, frame: Frame) -> Optional[DepthOutput]:
        """Process one frame; returns the depth output that became ready (or None). See docs/estimator.md."""
        t0 = time.perf_counter()
        self._frames_received += 1
        image = checked_image(frame)
        drop = drop_reason(frame)
        if drop is not None:
            self._frames_dropped += 1
            self._last_drop_reason = drop
            if 'pose' in drop:
                self._tracking = 'no pose'
            return None
        if self.config.reject_degenerate_frames:
            quality = image_quality.assess(image)
            self.last_image_quality = quality
            if not quality.ok:
                # no filter update, no keyframe, nothing published (see _degenerate_frame)
                return self._degenerate_frame(quality)
        T = np.asarray(frame.T_world_cam_44, dtype=np.float64)
        K_in = np.asarray(frame.K_33, dtype=np.float64)
        size = (int(image.shape[1]), int(image.shape[0]))
        stamp = float(frame.stamp)
        if self._last_frame is not None and time_order(self._last_frame[0], stamp) == DUPLICATE:
            self._frames_dropped += 1
            self._last_drop_reason = f'duplicate stamp {stamp:.6f} s (same as the previous frame)'
            return None
        reset = self._stream_reset_reason(stamp, T, size, K_in, frame.sensor_gap_s)
        if reset is not None:
            self.reset(reset)
        # the camera's velocity, for the time-sync term of the pose uncertainty (only where that term is used)
        uses_sync = self.config.pose_uncertainty in ('auto', 'drift') and self.config.odom_time_sync_ms > 0
        self._twist = None if self._last_frame is None or not uses_sync else \
            pose_uncertainty.twist_between(self._last_frame[1], T, stamp - self._last_frame[0])
        self._last_frame = (stamp, T, size, K_in)
        self._frames_accepted += 1
        frame_index = self._frames_accepted - 1
        decision = self.selector.decide(T)
        with torch.no_grad():
            if not decision.is_keyframe:
                out = self._between_output(frame, T, size, K_in, t0)
            else:
                out = self._keyframe(frame, image, T, size, K_in, frame_index, t0)
        if out is not None:
            self._outputs += 1
        return out

    # ------------------------------------------------------------------ checks
    def _degenerate_frame(self, quality: 'image_quality.ImageQuality') -> None:
        """A frame that carries no depth information (``image_quality.assess``): counted as dropped and as
        degenerate (``status.frames_degenerate``, ``status.last_degenerate_reason``); the window, the
        keyframe selector, the filter and the stream state are left exactly as they were."""
        self._frames_dropped += 1
        self._frames_degenerate += 1
        self._last_degenerate_reason = quality.reason
        self._last_drop_reason = f'degenerate image ({quality.reason})'
        return None

    def _stream_reset_reason(self, stamp: float, T: np.ndarray, size, K_in,
                             sensor_gap_s: Optional[float] = None) -> Optional[str]:
        """Why the stream must restart at this frame (``continuity.stream_break``), or None."""
        cfg = self.config
        return stream_break(self._last_frame, stamp, T, size, K_in, sensor_gap_s, reset_time_gap=cfg.reset_time_gap,
                            max_speed=cfg.odom_max_speed, max_rate_deg=cfg.odom_max_rate_deg)

    # ------------------------------------------------------------------ keyframes
    def _prepare(self, image: np.ndarray, K_in: np.ndarray) -> Tuple[torch.Tensor, np.ndarray]:
        """Processing-size image (1, 3, H, W) float [0, 1] on the device and its K (numpy)."""
        W, H = self.config.processing_size
        h0, w0 = image.shape[:2]
        if (w0, h0) != (W, H):
            interp = cv2.INTER_AREA if (W <= w0 and H <= h0) else cv2.INTER_LINEAR
            image = cv2.resize(image, (W, H), interpolation=interp)
        K = scale_intrinsics_np(K_in, W / w0, H / h0)
        t = torch.from_numpy(np.ascontiguousarray(image)).to(self.device)
        t = t.permute(2, 0, 1)[None].float().div_(255.0)
        return t.contiguous(), K

    def _keyframe(self, frame, image, T, size, K_in, frame_index, t0) -> Optional[DepthOutput]:
        timings: Dict[str, float] = {}
        t = time.perf_counter()
        img_t, K_proc = self._prepare(image, K_in)
        kf = Keyframe(index=self._kf_counter, frame_index=frame_index, stamp=float(frame.stamp),
                      T_world_cam_44=self._chain_pose(T), image_b3hw=img_t,
                      K_b33=torch.as_tensor(K_proc, dtype=torch.float32, device=self.device)[None],
                      input_size=size, input_K_33=K_in, frame_id=frame.frame_id, odom_T_world_cam_44=T,
                      twist_world_6=self._twist,
                      pose_cov_66=window_pose_uncertainty.frame_covariance(self.config, frame),
                      twist_cov_66=window_pose_uncertainty.frame_covariance(self.config, frame, 'twist'),
                      camera_gray_u8=to_gray_u8(image) if getattr(self.pose_refiner, 'uses_camera_images',
                                                                   False) else None)
        self._kf_counter += 1
        self._keyframes += 1
        self.window.append(kf)
        timings['resize'] = self._ms(t)
        sel = self.window.select(self.config.window_mode, **self._source_scoring())
        if sel is None:
            self._tracking = 'waiting for keyframes'
            self._last_timings = dict(timings, total=self._ms(t0))
            return None
        ref, sources = sel
        lost = self._refine_poses(ref, sources, timings)
        if lost is not None and self.config.odometry == 'topic':
            # with odometry from a topic a failed refinement is no tracking loss: the refiner returned the odometry
            # motion chained onto its last good poses for this window; keep the belief and go on
            self._refine_fallbacks += 1
            self._last_refine_fallback_reason = lost
            lost = None
        if lost is not None:
            # the refiner (visual odometry) lost tracking: restart the filter, publish nothing for this keyframe
            self.filter.reset()
            self._posterior = None
            self._anchor_T_world = None
            reason = f'pose refinement lost tracking: {lost}'
            self._resets += 1
            self._last_reset_reason = reason
            self._pending_reset_reason = reason
            self._tracking = 'pose tracking lost'
            self._last_timings = dict(timings, total=self._ms(t0))
            return None

        t = time.perf_counter()
        T_src_ref = np.stack([np.linalg.inv(s.T_world_cam_44) @ ref.T_world_cam_44 for s in sources])
        T_src_ref_t = torch.as_tensor(T_src_ref, dtype=torch.float32, device=self.device)[None]   # 1,N,4,4
        meas = self._measure(ref, sources, T_src_ref_t, timings)
        timings['measurement'] = self._ms(t)
        if 'measurement.features' in timings:
            timings['measurement.cost_volume'] = timings['measurement'] - timings['measurement.features']

        t = time.perf_counter()
        vol_hw = tuple(meas.logp_bdhw.shape[-2:])
        coverage = keyframe_geometry.coverage(self.config, meas.K_vol_b33, vol_hw, T_src_ref_t[0], self.depths_d)
        geom = keyframe_geometry.sweep_geometry(self.config, meas.logp_bdhw, meas.K_vol_b33, ref.K_b33, T_src_ref_t,
                                                vol_hw, self.depths_d, self.readout)
        weight, self._last_parallax = keyframe_geometry.parallax_weight(self.config, geom, ref.K_b33, T_src_ref_t)
        t_pose = time.perf_counter()
        # the window refiner's marginals (relative to the reference), where it solved this window, replace the
        # odometry's uncertainty of those sources
        sigma_planes, self._last_pose_sigma = window_pose_uncertainty.window_sigma_planes(
            self.config, geom, ref, sources, meas.K_vol_b33,
            geometry.inverse_depth_step(self.d_min, self.d_max, self.num_planes),
            marginals=getattr(self._refinement_result(), 'source_sigma', None))
        if sigma_planes is not None:
            meas.logp_bdhw = pose_uncertainty.widen_planes(meas.logp_bdhw, sigma_planes)
            timings['pose_uncertainty'] = self._ms(t_pose)
        self._knet_ms = 0.0
        step = self.filter.step(meas.logp_bdhw.float(), meas.K_vol_b33, self._filter_pose(ref.T_world_cam_44),
                                ref.stamp, self.depths_d, image_b3hw=ref.image_b3hw, update_weight_bhw=weight)
        if self.filter_mode == 'knet':
            timings['filter.knet'] = self._knet_ms
        post = step.logp_bdhw
        support = keyframe_geometry.carry_support(step.predicted_logp_bdhw, weight, self._posterior,
                                                  ref.T_world_cam_44, meas.K_vol_b33, self.depths_d, self.readout)
        self._posterior = _Posterior(post, ref.T_world_cam_44.copy(), meas.K_vol_b33, coverage, ref.stamp,
                                     support)
        # the stages add up to the total: the pose-uncertainty step ran inside this one and is its own stage
        timings['filter'] = self._ms(t) - timings.get('pose_uncertainty', 0.0)

        t = time.perf_counter()
        H, W = ref.image_b3hw.shape[-2:]
        K_proc_t = ref.K_b33[0]
        if self.measurement == 'network':
            full = self.nets.refine(post, meas.feats, ref.image_b3hw)
            timings['refine.rnet'] = self._ms(t)
            depth, conf = self._readout(full, ref.image_b3hw, timings=timings, stage='refine')
            band_mass = conf
            if sigma_planes is not None:
                factor = window_pose_uncertainty.confidence_factor(self.config, post, sigma_planes, self.depths_d,
                                                                   self.readout)
                conf = conf * resample_to_camera(factor[:, None], meas.K_vol_b33[0], K_proc_t, (H, W))[:, 0]
            if support is not None:
                conf = conf * resample_to_camera(support[:, None], meas.K_vol_b33[0], K_proc_t, (H, W))[:, 0]
            valid = resample_to_camera(coverage[:, None].float(), meas.K_vol_b33[0], K_proc_t, (H, W),
                                       mode='nearest')[:, 0] > 0.5
            timings['refine'] = self._ms(t)
        else:
            depth_v, conf_v = self._readout(post, None, sigma_planes, timings=timings, stage='upsample')
            if support is not None:
                conf_v = conf_v * support
            depth, conf, valid = volume_maps_to_processing(
                depth_v, conf_v, coverage,
                meas.K_vol_b33[0], K_proc_t, (H, W))
            timings['upsample'] = self._ms(t)

        t = time.perf_counter()
        fallback = None if self.fallback is None else self.fallback.opinion(ref, sources, T_src_ref_t, timings)
        belief = self.filter.logp_bdhw
        depth, conf, anchor_report = self._hold_to_anchors(ref, depth, conf, fallback)
        if self.filter.logp_bdhw is not belief:         # anchor_target: belief moved it: the frames between follow
            self._posterior.logp_bdhw, self._posterior.median_depth = self.filter.logp_bdhw, None
        timings['anchors'] = self._ms(t)

        t = time.perf_counter()
        reason = self._take_reset_reason(step.reset_reason)
        out = compose_output(self.config, depth, conf, valid, ref.input_size, ref.input_K_33, ref.stamp,
                             ref.T_world_cam_44, True, reason, self.calibration)
        timings['output'] = self._ms(t)
        out.anchors = anchor_report
        if self.collect_features and self.measurement == 'network':
            out.features = confidence_features.keyframe_features(
                full_logp_bdhw=full, depth_bhw=depth, band_mass_bhw=band_mass, conf_bhw=conf, depths_d=self.depths_d,
                ratio=self.config.confidence_ratio, readout=self.readout, ref_image_b3hw=ref.image_b3hw,
                src_images=[s.image_b3hw for s in sources], K_proc_b33=ref.K_b33, T_src_ref_n44=T_src_ref_t[0],
                K_vol_33=meas.K_vol_b33[0], measured_logp_bdhw=meas.logp_bdhw,
                predicted_logp_bdhw=step.predicted_logp_bdhw, spans_n1hw=None if geom is None else geom[1],
                weight_bhw=weight, support_bhw=support, sigma_planes_bhw=sigma_planes)
        timings['total'] = self._ms(t0)
        out.timings_ms = timings
        self._last_timings = dict(timings)
        self._tracking = 'tracking'
        return out

    def _hold_to_anchors(self, ref: Keyframe, depth_bhw: torch.Tensor, conf_bhw: torch.Tensor, fallback=None):
        """(depth, confidence, report) of the keyframe held to its metric anchors; ``fallback``: the sweep's."""
        return metric_anchors.hold_to_anchors(self.anchors, self.pose_refiner, self._refinement_result(),
                                              float(ref.stamp), ref.K_b33[0], depth_bhw, conf_bhw, fallback,
                                              self.filter if self.config.anchor_target == 'belief' else None)

    def _chain_pose(self, T_odom_44: np.ndarray) -> np.ndarray:
        """Pose estimate of a new frame: its odometry motion since the newest keyframe chained onto that
        keyframe's (possibly refined) pose. Without pose refinement this is the odometry pose itself."""
        newest = self.window.newest
        if newest is None:
            return np.array(T_odom_44, dtype=np.float64, copy=True)
        return newest.T_world_cam_44 @ np.linalg.inv(newest.odom_T_world_cam_44) @ T_odom_44

    def _filter_pose(self, T_world_cam_44: np.ndarray) -> torch.Tensor:
        """(1, 4, 4) float32 pose for the filter, relative to an anchor (the first keyframe since the last
        reset), computed in float64: the filter only uses relative poses, and large world coordinates
        (odometry hundreds of metres from its origin) would lose millimetres in float32."""
        if self._anchor_T_world is None:
            self._anchor_T_world = np.linalg.inv(np.asarray(T_world_cam_44, dtype=np.float64))
        T = self._anchor_T_world @ np.asarray(T_world_cam_44, dtype=np.float64)
        return torch.as_tensor(T, dtype=torch.float32, device=self.device)[None]

    def _take_reset_reason(self, filter_reason: Optional[str]) -> Optional[str]:
        """The reset reason of this output: the estimator's own (pending since its reset; the filter was
        reset with it, so the filter's 'first frame' adds nothing), else the filter's."""
        reason = self._pending_reset_reason or filter_reason
        self._pending_reset_reason = None
        return reason

    def _readout(self, logp_bdhw: torch.Tensor, guide_b3hw: Optional[torch.Tensor] = None,
                 sigma_planes_bhw: Optional[torch.Tensor] = None, timings: Optional[Dict[str, float]] = None,
                 stage: str = '') -> Tuple[torch.Tensor, torch.Tensor]:
        """(depth, confidence), each (B, H, W), of a DPV with the configured ``depth_readout`` and
        ``confidence``; with ``depth_subplane`` the depth is refined between planes
        (``dpv.subplane_depth``), and with a colour ``guide_b3hw`` of the same size and
        ``edge_filter_radius`` > 0 it is then filtered edge-aware: the weighted median of its neighbourhood,
        weighted by confidence and colour similarity (``edge_filter.joint_weighted_median``). With ``timings``
        the two parts are timed there as ``<stage>.readout`` and ``<stage>.edge_filter``."""
        cfg = self.config
        t = time.perf_counter()
        depth = dpv_ops.depth_estimate(logp_bdhw, self.depths_d, self.readout)
        if cfg.depth_subplane:
            depth = dpv_ops.subplane_depth(logp_bdhw, self.depths_d, depth)
        conf = dpv_ops.published_confidence(logp_bdhw, self.depths_d, depth, cfg.confidence, cfg.confidence_ratio,
                                            sigma_planes_bhw)
        if timings is not None:
            timings[f'{stage}.readout'] = self._ms(t)
        if guide_b3hw is not None and cfg.edge_filter_radius > 0 and guide_b3hw.shape[-2:] == depth.shape[-2:]:
            t = time.perf_counter()
            depth = joint_weighted_median(depth, conf, guide_b3hw, cfg.edge_filter_radius, cfg.edge_filter_step,
                                          cfg.edge_filter_sigma)
            if timings is not None:
                timings[f'{stage}.edge_filter'] = self._ms(t)
        return depth, conf

    @staticmethod
    def _ms(t: float) -> float:
        return (time.perf_counter() - t) * 1000.0

    # ------------------------------------------------------------------ pose refinement hook
    def _refine_poses(self, ref: Keyframe, sources: List[Keyframe], timings: Dict[str, float]) -> Optional[str]:
        """Call the pose refiner (if any) on the window; returns a reason when it reports lost tracking
        (a refiner may expose ``tracking_lost`` and ``last_result.reason``), else None."""
        if self.pose_refiner is None:
            return None
        t = time.perf_counter()
        kfs = sorted([ref] + list(sources), key=lambda k: k.index)
        r = kfs.index(ref)
        depth = conf = K_depth = None
        stride = int(getattr(self.pose_refiner, 'predicted_depth_stride', 1))
        pred = self.filter.predict(self._filter_pose(ref.T_world_cam_44), stride=stride)
        if pred is not None and self._posterior is not None:
            # the refiner maps the +-1-plane mass to an inverse-depth std, whatever the published confidence is
            depth = dpv_ops.depth_estimate(pred, self.depths_d, self.readout)
            depth, conf = depth[0], dpv_ops.confidence(pred, self.depths_d, depth_bhw=depth)[0]
            K_depth = subsampled_intrinsics(self._posterior.K_vol_b33[0].double().cpu().numpy(), stride)
        request = PoseRefinementRequest(kfs, r, depth, conf, K_depth, self.depths_d)
        timings['pose_refinement.predict'] = self._ms(t)
        last = getattr(self.pose_refiner, 'last_result', None)
        try:
            refined = self.pose_refiner(request)
        except Exception as exc:  # a failing refiner must not stop the sensor
            self._note(f'pose refiner failed ({type(exc).__name__}: {exc}); using the unrefined poses')
            refined = None
        if refined is not None:
            refined = [np.asarray(T, dtype=np.float64) for T in refined]
            if len(refined) != len(kfs) or not all(T.shape == (4, 4) and np.all(np.isfinite(T)) and is_rigid(T)
                                                   for T in refined):
                self._note('pose refiner returned an invalid result (count, shape or non-rigid pose); ignored')
            else:
                for kf, T in zip(kfs, refined):
                    kf.T_world_cam_44 = T.copy()
        timings['pose_refinement'] = self._ms(t)
        result = getattr(self.pose_refiner, 'last_result', None)
        if result is not None and result is not last:      # the parts the refiner timed in this call
            for part in ('align', 'keypoints', 'optimize'):
                if part in getattr(result, 'timings_ms', {}):
                    timings[f'pose_refinement.{part}'] = float(result.timings_ms[part])
        skipped = getattr(result, 'skipped', None)
        if skipped:
            # the refiner kept the odometry for this window (e.g. the camera turns in place): a fallback
            self._refine_fallbacks += 1
            self._last_refine_fallback_reason = str(skipped)
        if getattr(self.pose_refiner, 'tracking_lost', False):
            result = getattr(self.pose_refiner, 'last_result', None)
            return str(getattr(result, 'reason', None) or 'the refiner reports tracking loss')
        return None

    # ------------------------------------------------------------------ measurement
    def _measure(self, ref: Keyframe, sources: List[Keyframe], T_src_ref_t: torch.Tensor,
                 timings: Dict[str, float]) -> _Measurement:
        if self.measurement == 'network':
            with self._autocast():
                t = time.perf_counter()
                for kf in [ref] + list(sources):
                    if 'features' not in kf.cache:
                        kf.cache['features'] = self.nets.extract_features(kf.image_b3hw)
                timings['measurement.features'] = self._ms(t)
                logp, K_vol, feats = self.model.measure(
                    ref.image_b3hw, None, ref.K_b33, T_src_ref_t,
                    src_features=[s.cache['features'] for s in sources], ref_features=ref.cache['features'])
            return _Measurement(logp.float(), K_vol.float(), feats)
        srcs = torch.stack([s.image_b3hw[0] for s in sources])[None]                 # 1,N,3,H,W
        logp, K_vol = self.classical(ref.image_b3hw, srcs, ref.K_b33, T_src_ref_t)
        return _Measurement(logp.float(), K_vol.float())

    # ------------------------------------------------------------------ parallax
    def _source_scoring(self) -> Dict[str, Any]:
        """Keyword arguments of ``KeyframeWindow.select`` for choosing sources from the pool (``source_pool``):
        ``parallax.pose_parallax_score`` at a nominal depth (the median depth of the last posterior, else the
        middle of the planes in inverse depth), ``min_score`` = ``parallax_full_px`` (or 1 px when that rule is
        off). Empty when there is no pool."""
        cfg = self.config
        if cfg.source_pool <= cfg.window_size:
            return {}
        depth = self._nominal_depth()

        def score(ref: Keyframe, kf: Keyframe) -> float:
            H, W = ref.image_b3hw.shape[-2:]
            return parallax.pose_parallax_score(ref.T_world_cam_44, kf.T_world_cam_44,
                                                ref.K_b33[0].double().cpu().numpy(), (H, W), depth)
        return {'score': score, 'min_score': cfg.parallax_full_px if cfg.parallax_full_px > 0 else 1.0}

    def _nominal_depth(self) -> float:
        """A typical depth of the scene: the median depth of the last posterior (volume resolution), else the
        middle of the depth planes in inverse depth."""
        p = self._posterior
        if p is not None:
            if getattr(p, 'median_depth', None) is None:
                d = dpv_ops.depth_estimate(p.logp_bdhw, self.depths_d, self.readout)
                p.median_depth = float(d[p.coverage_bhw].median()) if bool(p.coverage_bhw.any()) else None
            if p.median_depth is not None and math.isfinite(p.median_depth):
                return p.median_depth
        return 2.0 / (1.0 / self.d_min + 1.0 / self.d_max)

    # ------------------------------------------------------------------ outputs
    def _between_output(self, frame: Frame, T, size, K_in, t0) -> Optional[DepthOutput]:
        """A non-keyframe: the filter's posterior warped into this frame's pose (no network run)."""
        cfg = self.config
        p = self._posterior
        if not cfg.publish_between_keyframes or cfg.window_mode != 'causal' or p is None:
            return None
        t = time.perf_counter()
        T = self._chain_pose(T)
        T_cur_prev = np.linalg.inv(T) @ p.T_world_cam_44
        T_t = torch.as_tensor(T_cur_prev, dtype=torch.float32, device=self.device)[None]
        pred, inside = geometry.warp_volume(p.logp_bdhw, p.K_vol_b33, T_t, self.depths_d, return_valid=True)
        depth_v, conf_v = self._readout(pred)
        # valid: most of the ray lies in the posterior's frustum, and the estimated surface point falls on
        # a pixel of the keyframe that had an estimate
        valid_v = inside.float().mean(1) >= cfg.min_coverage
        T_prev_cur = torch.as_tensor(np.linalg.inv(T_cur_prev), dtype=torch.float32, device=self.device)[None]
        maps = p.coverage_bhw[:, None].float()
        if p.support_bhw is not None:      # the parallax support travels with the belief
            maps = torch.cat([maps, p.support_bhw[:, None]], 1)
        cov, ok = geometry.warp_image_with_depth(maps, depth_v, p.K_vol_b33, p.K_vol_b33, T_prev_cur)
        valid_v = valid_v & ok & (cov[:, 0] > 0.5)
        if p.support_bhw is not None:
            conf_v = conf_v * cov[:, 1]
        W, H = cfg.processing_size
        K_proc = torch.as_tensor(scale_intrinsics_np(K_in, W / size[0], H / size[1]), dtype=torch.float32,
                                 device=self.device)
        depth, conf, valid = volume_maps_to_processing(depth_v, conf_v, valid_v, p.K_vol_b33[0], K_proc, (H, W))
        out = compose_output(self.config, depth, conf, valid, size, K_in, float(frame.stamp), T, False, None,
                             self.calibration)
        out.timings_ms = {'between': self._ms(t), 'total': self._ms(t0)}
        self._last_timings = dict(out.timings_ms)
        return out
