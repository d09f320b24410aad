"""The node's parameters: one typed, range-checked table (no ROS import).

The node declares exactly these (with descriptors built from this table), `config/dpv_sensor.yaml` documents
them with the same defaults (a test keeps the two in step), and `validate()` rejects bad values at start with a
message naming the parameter, the value and the allowed range.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Sequence


@dataclass(frozen=True)
class ParamSpec:
    name: str
    default: Any
    description: str
    choices: Sequence[Any] | None = None
    min_value: float | None = None
    max_value: float | None = None
    length: int | None = None  # fixed length of an array parameter

    @property
    def kind(self) -> type:
        return type(self.default)


IDENTITY_POSE = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]

SPECS: tuple[ParamSpec, ...] = (
    # --- model --------------------------------------------------------------------------------------------
    ParamSpec('preset', 'lite', 'Network preset: lite (2-core CPU) or paper (the appendix tables).',
              choices=('lite', 'paper')),
    ParamSpec('weights', '', 'Checkpoint (.safetensors). Empty: the packaged weights of the preset. '
              'When no weights load, the node warns and falls back to the classical (NCC) model.'),
    ParamSpec('measurement', 'auto', 'Measurement model: auto (network, classical fallback), network or classical.',
              choices=('auto', 'network', 'classical')),
    ParamSpec('device', 'cpu', 'Torch device: cpu, cuda or cuda:N.'),
    ParamSpec('torch_threads', 0, 'CPU threads for torch (torch.set_num_threads, applied when the estimator is '
              'built; process-wide). 0 leaves torch\'s default. On a loaded 2-core machine 1 gives the steadiest '
              'latency.', min_value=0, max_value=64),
    ParamSpec('cpu_precision', 'auto', 'What the networks compute in on the CPU: auto (bfloat16 where the CPU has '
              'AMX or AVX512-BF16 kernels, else float32), float32, or bfloat16 (autocast; a lite keyframe 1.25x '
              '(320x256) to 1.4x (640x480) faster with those kernels, emulated and slower without). Geometry, '
              'filter and DPV normalisations stay float32; on CUDA the networks always run under bfloat16 '
              'autocast. bfloat16 held about 90 MB more resident memory than float32 in a 30-minute soak (bounded; '
              'peaks to 1.5 GB) before the node capped glibc\'s malloc arenas at two, which brought it lower.',
              choices=('auto', 'float32', 'bfloat16')),
    ParamSpec('processing_width', 320, 'Width the images are resized to for estimation (pixels).',
              min_value=32, max_value=4096),
    ParamSpec('processing_height', 256, 'Height the images are resized to for estimation (pixels).',
              min_value=32, max_value=4096),
    ParamSpec('d_min', 0.3, 'Nearest depth plane (m), used by the classical model; networks use their checkpoint.',
              min_value=0.01, max_value=100.0),
    ParamSpec('d_max', 8.0, 'Farthest depth plane (m), used by the classical model.', min_value=0.1, max_value=1000.0),
    ParamSpec('num_planes', 64, 'Depth planes of the classical model.', min_value=4, max_value=256),
    # --- filter -------------------------------------------------------------------------------------------
    ParamSpec('filter_mode', 'knet', 'DPV filter update: none, bayes, global or knet '
              '(knet needs network weights; falls back to global).', choices=('none', 'bayes', 'global', 'knet')),
    ParamSpec('depth_readout', 'auto', 'How the DPV becomes one depth per pixel: relative (the depth with the '
              'least expected relative error, the median of p(d)/d), median (least absolute error), mean (the '
              'expectation, paper eq. 1; lands between the modes of a two-mode DPV) or auto (relative with the '
              'network, mean with the classical model, whose flat DPVs the other two pull to the near planes).',
              choices=('auto', 'relative', 'median', 'mean')),
    ParamSpec('damping', 0.8, 'Global damping lambda of the prediction energy (paper eq. 8).',
              min_value=0.0, max_value=1.0),
    ParamSpec('reset_time_gap', 1.0, 'Reset the filter when the camera stream itself has a gap longer than this '
              '(s): two consecutive received images further apart. Images the node drops while busy do not '
              'count. 0 disables.', min_value=0.0, max_value=3600.0),
    ParamSpec('reset_translation', 1.0, 'Reset the filter when the camera jumps: moves more than this (m) per '
              'second of elapsed time between processed frames, and never less than this (frames under 1 s '
              'apart are held to it). Continuous motion across dropped frames or distant keyframes does not '
              'reset. 0 disables.', min_value=0.0, max_value=1000.0),
    ParamSpec('reset_rotation_deg', 45.0, 'Reset the filter when the camera turns more than this (deg) per second '
              'of elapsed time between processed frames, and never less than this (as reset_translation). '
              '0 disables.', min_value=0.0, max_value=180.0),
    # --- keyframes and window -----------------------------------------------------------------------------
    ParamSpec('window_mode', 'causal', 'causal: past keyframes only (no latency); centered: the paper window, two '
              'keyframes of latency.', choices=('causal', 'centered')),
    ParamSpec('keyframe_translation', 0.05, 'New keyframe after this baseline since the last one (m).',
              min_value=0.0, max_value=100.0),
    ParamSpec('keyframe_rotation_deg', 5.0, 'New keyframe after this rotation since the last one (deg).',
              min_value=0.0, max_value=180.0),
    ParamSpec('keyframe_max_interval', 5, 'New keyframe at the latest every this many frames (paper: 5).',
              min_value=1, max_value=1000),
    ParamSpec('publish_between_keyframes', False, 'Also publish a cheap depth for frames between keyframes, from '
              'the predicted DPV.'),
    # --- poses --------------------------------------------------------------------------------------------
    ParamSpec('odometry', 'topic', 'Pose source: topic (nav_msgs/Odometry on `odom`) or none (visual alignment).',
              choices=('topic', 'none')),
    ParamSpec('T_base_camera', list(IDENTITY_POSE), 'Static camera pose in the odometry child frame: '
              '[x, y, z, qx, qy, qz, qw] (identity: odometry already tracks the optical frame).', length=7),
    ParamSpec('odom_wait_timeout', 0.5, 'How long an image waits for odometry that brackets its stamp (s).',
              min_value=0.0, max_value=60.0),
    ParamSpec('max_odom_gap', 0.5, 'Largest gap between the two odometry messages an image pose is '
              'interpolated from (s).', min_value=0.0, max_value=60.0),
    ParamSpec('odom_max_speed', 10.0, 'An odometry step faster than this (m/s, and over 0.1 m) is a teleport: the '
              'pose buffer restarts and so does the estimator. 0 disables.', min_value=0.0, max_value=1e4),
    ParamSpec('odom_max_rate_deg', 720.0, 'An odometry step turning faster than this (deg/s, and over 10 deg) is a '
              'teleport (as odom_max_speed). 0 disables.', min_value=0.0, max_value=1e6),
    ParamSpec('publish_tf', False, 'Publish TF: base_frame -> image frame (T_base_camera) on /tf_static, and with '
              'pose_refinement or odometry none the estimated pose as <image frame>_refined on /tf. Off by default: '
              'the camera driver or a URDF normally publishes the image frame already, and a second parent makes '
              'tf2 lookups of that frame flip between the two; turn it on when nothing else puts the camera in TF '
              '(a replayed bag without /tf_static, a webcam).'),
    ParamSpec('base_frame', '', 'Parent frame of the static TF: the frame T_base_camera is given in. Empty: the '
              'odometry\'s child_frame_id.'),
    ParamSpec('pose_refinement', 'off', 'Sliding-window pose refinement with gtsam: off or window.',
              choices=('off', 'window')),
    ParamSpec('odom_sigma_rot_deg', 0.5, 'Pose refinement: rotation std of the odometry between two keyframes '
              '(deg); lower trusts odometry more.', min_value=1e-4, max_value=90.0),
    ParamSpec('odom_sigma_trans_m', 0.002, 'Pose refinement: translation std of the odometry between two keyframes, '
              'constant part (m).', min_value=1e-6, max_value=10.0),
    ParamSpec('odom_sigma_trans_rel', 0.03, 'Pose refinement: translation std of the odometry between two keyframes, '
              'part proportional to the distance travelled (0.03 = 3 %).', min_value=0.0, max_value=10.0),
    # --- camera -------------------------------------------------------------------------------------------
    ParamSpec('camera_info_source', 'topic', 'Intrinsics from the camera_info topic or from the fx/fy/cx/cy '
              'parameters.', choices=('topic', 'parameters')),
    ParamSpec('fx', 0.0, 'Focal length x (px) when camera_info_source is parameters.', min_value=0.0),
    ParamSpec('fy', 0.0, 'Focal length y (px).', min_value=0.0),
    ParamSpec('cx', 0.0, 'Principal point x (px).', min_value=0.0),
    ParamSpec('cy', 0.0, 'Principal point y (px).', min_value=0.0),
    # --- output -------------------------------------------------------------------------------------------
    ParamSpec('depth_encoding', '32FC1', 'depth/image encoding: 32FC1 metres (NaN = none) or 16UC1 millimetres '
              '(0 = none), REP 118.', choices=('32FC1', '16UC1')),
    ParamSpec('output_resolution', 'input', 'Output image size: input (the camera\'s) or processing.',
              choices=('input', 'processing')),
    ParamSpec('confidence', 'ratio', 'What the confidence image holds: ratio (the probability under the DPV that '
              'the true depth is within a factor confidence_ratio of the published one, i.e. that the pixel is '
              'correct by the delta < 1.25 measure) or plane (the DPV mass within one depth plane of it, paper '
              'eq. 2 made independent of where the depth falls between planes).', choices=('ratio', 'plane')),
    ParamSpec('confidence_ratio', 1.25, 'Factor of the ratio confidence: the band [d/ratio, d*ratio] around '
              'the published depth d.', min_value=1.01, max_value=10.0),
    ParamSpec('min_confidence', 0.0, 'Depth with lower confidence is published as no estimate.',
              min_value=0.0, max_value=1.0),
    # --- transport ----------------------------------------------------------------------------------------
    ParamSpec('input_reliability', 'best_effort', 'QoS reliability of the subscriptions (sensor data default).',
              choices=('best_effort', 'reliable')),
    ParamSpec('input_depth', 5, 'QoS history depth of the subscriptions.', min_value=1, max_value=1000),
    ParamSpec('output_reliability', 'reliable', 'QoS reliability of the publishers.',
              choices=('best_effort', 'reliable')),
    ParamSpec('output_depth', 5, 'QoS history depth of the publishers.', min_value=1, max_value=1000),
    ParamSpec('diagnostics_period', 1.0, 'Seconds between /diagnostics messages.', min_value=0.05, max_value=60.0),
)

SPEC_BY_NAME = {s.name: s for s in SPECS}


class ParameterError(ValueError):
    """A parameter value outside its type, choices or range."""


def defaults() -> dict[str, Any]:
    return {s.name: (list(s.default) if isinstance(s.default, list) else s.default) for s in SPECS}


def validate(values: dict[str, Any]) -> dict[str, Any]:
    """Check every known parameter; return the values with ints promoted where a float is expected.

    Raises ParameterError naming the first offending parameter.
    """
    out = dict(values)
    for spec in SPECS:
        if spec.name not in values:
            raise ParameterError(f"parameter '{spec.name}' is missing")
        value = values[spec.name]
        kind = spec.kind
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if kind is list:
            if not isinstance(value, (list, tuple)) or (spec.length and len(value) != spec.length):
                raise ParameterError(f"parameter '{spec.name}' must be a list of {spec.length} numbers, got {value!r}")
            value = [float(v) for v in value]
            if not all(math.isfinite(v) for v in value):
                raise ParameterError(f"parameter '{spec.name}' has a non-finite entry: {value!r}")
        elif not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
            raise ParameterError(f"parameter '{spec.name}' must be {kind.__name__}, got {value!r}")
        if spec.choices is not None and value not in spec.choices:
            raise ParameterError(f"parameter '{spec.name}' = {value!r} is not one of {list(spec.choices)}")
        if kind in (int, float):
            if not math.isfinite(value):
                raise ParameterError(f"parameter '{spec.name}' = {value!r} is not finite")
            if spec.min_value is not None and value < spec.min_value:
                raise ParameterError(f"parameter '{spec.name}' = {value!r} is below its minimum {spec.min_value}")
            if spec.max_value is not None and value > spec.max_value:
                raise ParameterError(f"parameter '{spec.name}' = {value!r} is above its maximum {spec.max_value}")
        out[spec.name] = value
    if out['d_min'] >= out['d_max']:
        raise ParameterError(f"d_min ({out['d_min']}) must be below d_max ({out['d_max']})")
    if out['camera_info_source'] == 'parameters' and min(out['fx'], out['fy']) <= 0.0:
        raise ParameterError("camera_info_source is 'parameters' but fx/fy are not set (> 0)")
    q = out['T_base_camera'][3:]
    if abs(math.sqrt(sum(c * c for c in q)) - 1.0) > 1e-3:
        raise ParameterError(f"T_base_camera quaternion {q} is not unit length")
    return out
