"""The settings tables: every setting's description, default, range and choices, written once.

``SPECS`` are the node's ROS parameters, in two scopes: ``estimator`` (fields of ``EstimatorConfig``, the
streaming core and its pose source: the same names offline, in ``evaluate --config`` and in the node) and
``node`` (topics, QoS, encodings, the odometry buffer, camera intrinsics: fields of :class:`NodeConfig`).
``LIBRARY_SPECS`` are estimator settings that are not node parameters (window size, volume scale, coverage,
autocast dtype). From this one table come: the node's parameter declarations (``node_params.declare_parameters``),
``EstimatorConfig`` and ``NodeConfig`` (:func:`make_config_class`), ``config/dpv_sensor.yaml``
(:func:`yaml_text`; a test keeps the file equal to it), the ``key=value`` parser of the tools
(:func:`parse_assignments`), and validation (:func:`check_value`, :func:`validate`), so a bad value is refused
with the same message by the node, the estimator and ``evaluate``. No ROS import here.
"""
from __future__ import annotations

import dataclasses
import math
import textwrap
from dataclasses import dataclass
from typing import Any, Iterable, Sequence

SCOPES = ('estimator', 'node', 'library')


@dataclass(frozen=True)
class ParamSpec:
    name: str
    default: Any
    description: str
    choices: Sequence[Any] | None = None
    min_value: float | None = None
    max_value: float | None = None
    length: int | None = None  # fixed length of an array parameter
    scope: str = 'estimator'   # one of SCOPES

    @property
    def kind(self) -> type:
        return type(self.default)

    def fresh_default(self) -> Any:
        """The default (a new list for array settings)."""
        return list(self.default) if isinstance(self.default, list) else self.default


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
              "built; process-wide). 0 leaves torch's default. On a loaded 2-core machine 1 gives the steadiest "
              'latency.', min_value=0, max_value=64),
    ParamSpec('cpu_precision', 'auto', 'What the networks compute in on the CPU: auto (bfloat16 where the CPU has '
              'AMX or AVX512-BF16 kernels, else float32), float32, or bfloat16 (autocast; a lite keyframe 1.25x '
              '(320x256) to 1.4x (640x480) faster with those kernels, emulated and slower without). Geometry, '
              'filter and DPV normalisations stay float32; on CUDA the networks always run under bfloat16 '
              'autocast. bfloat16 held about 90 MB more resident memory than float32 in a 30-minute soak (bounded; '
              "peaks to 1.5 GB) before the node capped glibc's malloc arenas at two, which brought it lower.",
              choices=('auto', 'float32', 'bfloat16')),
    ParamSpec('inference_backend', 'torch', 'What runs D-Net, K-Net and R-Net on the CPU: torch (PyTorch, the '
              'reference), onnxruntime (ONNX Runtime, float32) or openvino (OpenVINO, in cpu_precision). The ONNX '
              'files are exported from the loaded weights at start and cached (~/.cache/dpv_sensor/onnx); a runtime '
              'that is not installed or fails its check against PyTorch (1e-4) is reported once and PyTorch runs.',
              choices=('torch', 'onnxruntime', 'openvino')),
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
    ParamSpec('depth_subplane', False, "Shift the readout between depth planes by the sub-plane offset of the DPV's "
              'peak (vertex of a parabola through the log-probabilities of the mode and its neighbours, weighted '
              "by their mass). Off by default: the lite network's peaks sit farther than the relative readout, "
              'and on a rendered selection scene it raised abs_rel from 0.141 to 0.158.'),
    ParamSpec('edge_filter_radius', 4, 'Edge-aware refinement of the network depth: every depth becomes the '
              'weighted median of the pixels within this radius (processing pixels) sampled every 4 pixels (a 3x3 '
              'grid at 4), weighted by confidence and colour similarity, so depth edges move onto colour edges; '
              '0 = off.',
              min_value=0, max_value=32),
    ParamSpec('edge_filter_sigma', 0.08, "Colour distance (RGB in [0, 1]) at which a neighbour's vote in the "
              'edge-aware refinement falls to exp(-1/2): smaller keeps depth edges on weaker colour edges.',
              min_value=1e-3, max_value=1.0),
    ParamSpec('depth_anchors', 'dense', 'Metric anchors: points triangulated from the matches the pose-refinement '
              "window already makes and its metric poses check each keyframe's depth. off: not computed; scale: the "
              'depth multiplied by one robust, sigma-weighted scale fitted to them; dense: by a depth-aware scale '
              'map (each pixel corrected by the anchors near it in the image and in depth, unchanged where none '
              'is). The depth moves only by as much as it disagrees with its anchors beyond their sigma, and its '
              'confidence widens where it moved and where the disagreement was large. Keyframes with too few '
              'anchors (a camera turning in place), or whose odometry directions the images contradict, are '
              'unchanged. Needs pose_refinement: window.',
              choices=('off', 'scale', 'dense')),
    ParamSpec('anchor_judge', 'cautious', "Which map decides where the metric anchors overrule the networks' depth "
              '(dense anchors). cautious: the correcting map, whose pull towards no correction outweighs a few '
              'dozen anchors; counted: a map that counts each anchor near a pixel at its own weight (a kernel-'
              'weighted mean with its sigma, 16 bins of depth, at least three anchors of support), which catches a '
              'region put at twice its depth from about 40 anchors but follows clusters of biased anchors too (a '
              'rendered corridor 0.138 -> 0.155 abs_rel).',
              choices=('cautious', 'counted')),
    ParamSpec('anchor_fallback', 'off', "Where the metric anchors overrule the networks' depth (it disagrees "
              'with them by more than three sigma), off: the networks keep the overruled region, corrected to the '
              'anchors there, its confidence lowered; classical: the training-free plane sweep of the same keyframe '
              'is also computed, held to the same anchors, and blended in there by confidence (dense anchors only). '
              'Costs a sweep only on keyframes with overruled pixels; nothing when the measurement is already '
              'classical. off by default: on renders with a planted error the blend made the corrected depth worse.',
              choices=('classical', 'off')),
    ParamSpec('anchor_target', 'output', "Where the metric anchors' correction of a keyframe goes (dense or scale "
              "anchors). output: the published depth and confidence only; belief: the filter's belief as well, so "
              'the next keyframes start from the corrected depth (and from a wrong correction too).',
              choices=('belief', 'output')),
    ParamSpec('damping', 0.8, 'Global damping lambda of the prediction energy (paper eq. 8).',
              min_value=0.0, max_value=1.0),
    ParamSpec('reset_time_gap', 1.0, 'Reset the filter when the camera stream itself has a gap longer than this '
              '(s): two consecutive received images further apart. Images the node drops while busy do not '
              'count. 0 disables. The other resets are discontinuities only: time going backwards, a change of '
              'image size or intrinsics, a pose teleport (odom_max_speed, odom_max_rate_deg) and lost visual '
              'tracking; fast but smooth motion never resets, however far apart the processed frames are.',
              min_value=0.0, max_value=3600.0),
    # --- keyframes and window -----------------------------------------------------------------------------
    ParamSpec('window_mode', 'centered', 'centered: the paper window (reference = the middle of the window, sources on '
              'both sides); each depth image is published when the second keyframe after it has been processed, so '
              'it comes two keyframes late (about 1/3 s at 30 Hz and a keyframe every 5 frames, plus the keyframe '
              'time), with its own stamp. causal: past keyframes only, the low-latency option (published as soon as '
              'its keyframe is processed, same time per keyframe), at a cost in depth: on the rendered selection '
              'scenes with odometry-like noise abs_rel was 0.011 higher on average (5 of 6 scenes worse).',
              choices=('centered', 'causal')),
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
              '[x, y, z, qx, qy, qz, qw] (identity: odometry already tracks the optical frame).', length=7,
              scope='node'),
    ParamSpec('extrinsic_source', 'auto', 'Where the camera mount (odometry child frame -> image frame) comes from: '
              "parameter (T_base_camera), tf (looked up on /tf_static and /tf from the odometry's child_frame_id to "
              "the images' header.frame_id, chained through the frames between, as a URDF's robot_state_publisher "
              'or a camera driver publishes them; the latest transform is used) or auto (T_base_camera when it is '
              'not the identity, else tf: the identity is the default and the value the parameters file lists, so '
              'it cannot say that the user set it; with an identity mount between two differently named frames '
              'choose parameter). Images without a mount are dropped (dropped.no_extrinsic).',
              choices=('auto', 'tf', 'parameter'), scope='node'),
    ParamSpec('odom_wait_timeout', 0.5, 'How long an image waits for odometry that brackets its stamp (s).',
              min_value=0.0, max_value=60.0, scope='node'),
    ParamSpec('odom_time_offset_ms', 0.0, "The odometry's clock against the images': an image stamped t is paired "
              'with the odometry at t + this (ms; + when the odometry is stamped late). calibrate_mount and '
              "/diagnostics time_offset_estimate measure it.", min_value=-1000.0, max_value=1000.0, scope='node'),
    ParamSpec('max_odom_gap', 0.5, 'Largest gap between the two odometry messages an image pose is '
              'interpolated from (s).', min_value=0.0, max_value=60.0, scope='node'),
    ParamSpec('future_stamp_tolerance', 1.0, "An image stamped ahead of both the node's clock and the newest "
              'odometry by more than this (s) is dropped at once (dropped.future_stamp, a WARN naming how far ahead): '
              'no odometry can come for it by waiting; the camera clock and the odometry or node clock disagree '
              '(not synchronised), or the driver stamps wrongly. Not judged while the clock reads 0 (use_sim_time '
              'before /clock).', min_value=0.0, max_value=3600.0, scope='node'),
    ParamSpec('odom_max_speed', 10.0, 'A pose step faster than this (m/s, and over 0.1 m) is a teleport: between '
              'two odometry messages the pose buffer restarts and so does the estimator; between two frames pushed '
              'with their poses (offline) the estimator restarts. 0 disables.', min_value=0.0, max_value=1e4),
    ParamSpec('odom_max_rate_deg', 720.0, 'A pose step turning faster than this (deg/s, and over 10 deg) is a '
              'teleport (as odom_max_speed). 0 disables.', min_value=0.0, max_value=1e6),
    ParamSpec('publish_tf', False, 'Publish TF: base_frame -> image frame (T_base_camera) on /tf_static, and with '
              'pose_refinement or odometry none the estimated pose as <image frame>_refined on /tf. Off by default: '
              'the camera driver or a URDF normally publishes the image frame already, and a second parent makes '
              'tf2 lookups of that frame flip between the two; turn it on when nothing else puts the camera in TF '
              '(a replayed bag without /tf_static, a webcam).', scope='node'),
    ParamSpec('frame_id', 'camera_optical_frame', 'Frame of the outputs when an image arrives with an empty '
              'header.frame_id (warned once, counted in faults.empty_frame_id); otherwise the outputs carry the '
              "image's own frame. An optical frame (REP 103: z forward, x right, y down), as the depth is.",
              scope='node'),
    ParamSpec('base_frame', '', 'Parent frame of the static TF: the frame T_base_camera is given in. Empty: the '
              "odometry's child_frame_id.", scope='node'),
    ParamSpec('pose_refinement', 'window', 'Sliding-window pose refinement with gtsam: window or off. With the '
              'refine_* defaults the window holds the odometry as its covariance (else the odom_drift_* figures) '
              'says and corrects its rotation from matched keypoints; a window without enough matches, '
              'one that does not converge, moves a pose implausibly far from the odometry or turns in place keeps '
              'the odometry poses (counted in the pose_refinement_fallbacks diagnostic).',
              choices=('off', 'window')),
    ParamSpec('mount_check', True, "Estimate the camera mount's rotation and the camera-odometry time offset from "
              "the rotations the refinement window's matches measure between keyframes against the odometry's "
              '(hand-eye calibration, with a sigma each; needs odometry from a topic and pose_refinement window): '
              '/diagnostics mount_estimate and time_offset_estimate, and a WARN naming the estimate when it is '
              'confidently away from the mount and stamps in use. Reports only; nothing is changed.'),
    ParamSpec('odom_sigma_rot_deg', 0.5, 'Pose refinement: rotation std of the odometry between two keyframes '
              '(deg); lower trusts odometry more.', min_value=1e-4, max_value=90.0),
    ParamSpec('odom_sigma_trans_m', 0.002, 'Pose refinement: translation std of the odometry between two keyframes, '
              'constant part (m).', min_value=1e-6, max_value=10.0),
    ParamSpec('odom_sigma_trans_rel', 0.03, 'Pose refinement: translation std of the odometry between two keyframes, '
              'part proportional to the distance travelled (0.03 = 3 %).', min_value=0.0, max_value=10.0),
    ParamSpec('refine_odom_covariance', 'odometry', "Pose refinement: the odometry between factors' covariance. fixed: "
              'the odom_sigma_* above; odometry: what the odometry says about itself, the growth of the published '
              'pose covariance between two keyframes where it grows, else its twist covariance integrated over the '
              'step, else the odom_drift_* figures (per axis at most 5 deg / 0.10 m, the largest correction the '
              'window accepts: a huge covariance '
              'leaves the images to decide).',
              choices=('fixed', 'odometry')),
    ParamSpec('refine_photometric_sources', 0, 'Pose refinement: align the reference photometrically (against its '
              'predicted depth, paper eq. 11) to this many of its nearest sources, each a between factor. 0 (the '
              'default): keypoints and odometry only, half the time; the alignments follow the depth being '
              'estimated, which made the confidence over-confident under drift.', min_value=0, max_value=64),
    ParamSpec('refine_keypoints', True, 'Pose refinement: add relative-pose factors from matched keypoints between '
              'the reference and its two nearest sources (robust; what they hold: refine_keypoint_direction), '
              'evidence that does not depend on the depth being estimated.'),
    ParamSpec('refine_keypoint_direction', 'odometry', "Pose refinement with refine_keypoints: what a keypoint "
              "factor holds. odometry (the default): only the rotation, given the odometry's translation direction "
              "(the keypoints' rotation corrected by its correlation with the direction), the translation left to "
              "the odometry; keypoints: the rotation and the translation's direction of the matched keypoints, "
              "whose direction errs by several degrees on small indoor baselines.",
              choices=('keypoints', 'odometry')),
    ParamSpec('refine_rotation_evidence', 'auto', "Pose refinement with refine_keypoints: what the rotation "
              "factors are measured from. keypoints: SIFT matches at the processing size (refine_keypoint_direction "
              "says what they hold); flow: dense optical flow at the camera's resolution (up to 640 pixels wide), "
              "the rotation solved with the odometry's translation direction held fixed, between the reference and "
              "its two nearest sources, evidence that does not depend on the depth being estimated; auto (the "
              "default): flow while the images agree with the odometry's translation directions "
              "(refine_flow_direction_ratio), keypoints where they do not (a camera whose calibration, mount or "
              "timing does not match the odometry).",
              choices=('keypoints', 'flow', 'auto')),
    ParamSpec('refine_flow_max_width', 640, 'Pose refinement with the flow rotation factors: camera images wider '
              'than this are shrunk to it before the flow is measured (the metric anchors track on the same images). '
              'Narrower is faster and less precise: 320 took the pose refinement from 28 to 16 ms a keyframe, '
              'tripled the rotation error given the true direction (TartanAir 0.05 -> 0.15 deg) and made TUM '
              "fr1_rpy's depth 0.03 abs_rel worse with drifting odometry (docs/estimator.md).",
              min_value=64, max_value=4096),
    ParamSpec('refine_flow_direction_ratio', 1.05, "Pose refinement with refine_rotation_evidence auto: the flow "
              "factors are used while the median, over the last 50 flow pairs, of the matches' rms epipolar "
              "distance with the odometry's translation direction held over that with the direction fitted to the "
              "images stays at most this (about 1.02 where camera and odometry agree, 1.10 where they do not).",
              min_value=1.0, max_value=10.0),
    ParamSpec('refine_marginals', False, "Pose refinement: after a refined window, each source's pose covariance "
              "relative to the reference (gtsam marginals) widens the measurement and the confidence in place of "
              "the odometry's covariance and drift figures."),
    ParamSpec('refine_gate_chi2', 0.0, "Pose refinement: keep the odometry when a keypoint rotation differs from the "
              "odometry's by more than this chi-square under both covariances (3 dof; 16.27 = 99.9 %). 0 disables.",
              min_value=0.0, max_value=1e6),
    ParamSpec('refine_photometric_gate_chi2', 0.0, "Pose refinement with refine_photometric_sources: use a "
              "photometric alignment only when the rotation it moves the source by is one the odometry's own "
              "covariance allows (chi-square of the correction under the odometry step's rotation covariance, 3 dof; "
              "16.27 = 99.9 %); a larger one follows the depth it aligns against and is dropped (counted in "
              "/diagnostics pose_refinement_factors). 0 disables.", min_value=0.0, max_value=1e6),
    ParamSpec('refine_gate_min_inliers', 0, 'Pose refinement with refine_keypoints: keep the odometry when no '
              'keypoint pair has this many inliers (a textureless window). 0 disables.', min_value=0, max_value=100000),
    # --- camera -------------------------------------------------------------------------------------------
    ParamSpec('camera_info_source', 'topic', 'Intrinsics from the camera_info topic or from the fx/fy/cx/cy '
              'parameters.', choices=('topic', 'parameters'), scope='node'),
    ParamSpec('fx', 0.0, 'Focal length x (px) when camera_info_source is parameters.', min_value=0.0, scope='node'),
    ParamSpec('fy', 0.0, 'Focal length y (px).', min_value=0.0, scope='node'),
    ParamSpec('cx', 0.0, 'Principal point x (px).', min_value=0.0, scope='node'),
    ParamSpec('cy', 0.0, 'Principal point y (px).', min_value=0.0, scope='node'),
    # --- output -------------------------------------------------------------------------------------------
    ParamSpec('depth_encoding', '32FC1', 'depth/image encoding: 32FC1 metres (NaN = none) or 16UC1 millimetres '
              '(0 = none), REP 118.', choices=('32FC1', '16UC1'), scope='node'),
    ParamSpec('output_resolution', 'input', "Output image size: input (the camera's) or processing "
              "(processing_width wide, with the input's aspect ratio: 320x240 from 640x480, so that the output "
              "pairs with the camera's colour images; the height is rounded to whole pixels).",
              choices=('input', 'processing')),
    ParamSpec('confidence', 'ratio', 'What the confidence image holds: ratio (the probability under the DPV that '
              'the true depth is within a factor confidence_ratio of the published one, i.e. that the pixel is '
              'correct by the delta < 1.25 measure) or plane (the DPV mass within one depth plane of it, paper '
              'eq. 2 made independent of where the depth falls between planes).', choices=('ratio', 'plane')),
    ParamSpec('confidence_ratio', 1.25, 'Factor of the ratio confidence: the band [d/ratio, d*ratio] around '
              'the published depth d.', min_value=1.01, max_value=10.0),
    ParamSpec('parallax_full_px', 1.0, "Parallax rule: a keyframe's measurement counts fully where its window's "
              "baselines move a pixel's image by at least this many pixels (processing size) across the "
              'band [d/1.25, d*1.25] around its depth d, in proportion below; where they move it less (the camera '
              'turns in place) the filter keeps its predicted belief and the published confidence falls with '
              'the parallax the belief ever had (new pixels get none). 0 turns the rule off.',
              min_value=0.0, max_value=100.0),
    ParamSpec('parallax_rotation_noise', 0.05, "Parallax rule: a source's disparity counts against "
              'parallax_full_px plus this fraction of the image motion its rotation from the reference causes '
              '(f x angle): pose errors of real cameras (time sync, rolling shutter) grow with the rotation. '
              '0: rotation adds nothing.', min_value=0.0, max_value=1.0),
    ParamSpec('pose_uncertainty', 'covariance', "How each source's pose error relative to the reference widens "
              'its measurement (and so lowers the confidence where the pose error moves the match by more of the '
              "depth band than the parallax): covariance (the odometry's pose covariance's growth where it grows, "
              'else its twist covariance integrated over the time between two views; poses taken as exact '
              'otherwise), auto (the covariance, else the odom_drift_* and '
              'odom_time_sync_ms figures), drift (always those figures) or off. The figures are not the default: '
              'through the node they helped tum_fr1_rpy and ICL-NUIM (ECE -0.004 to -0.015) and cost SUN3D '
              '(+0.004 to +0.016) and some depth on SUN3D frag2 (+0.002 abs_rel).',
              choices=('covariance', 'auto', 'drift', 'off')),
    ParamSpec('odom_drift_trans', 0.02, 'Pose uncertainty: translation error of the odometry per metre travelled '
              '(0.02 = 2 %: wheel and visual-inertial odometry drift 0.5-3 % of the distance). Also caps the '
              "translation a published covariance's growth between two views is taken to mean (its growth holds the "
              'earlier heading error, which does not enter their relative motion).',
              min_value=0.0, max_value=1.0),
    ParamSpec('odom_drift_rot_deg_per_m', 1.0, 'Pose uncertainty: rotation error of the odometry (deg) per metre '
              'travelled.', min_value=0.0, max_value=90.0),
    ParamSpec('odom_drift_rot', 0.02, 'Pose uncertainty: rotation error of the odometry per degree turned '
              '(0.02 = 2 %: gyro scale error, timing).', min_value=0.0, max_value=1.0),
    ParamSpec('odom_time_sync_ms', 5.0, 'Pose uncertainty: std of the time offset between the camera images and '
              'the odometry (ms); pose error = offset x the change of velocity between two views.',
              min_value=0.0, max_value=1000.0),
    ParamSpec('source_pool', 0, "Choose the window's source keyframes from this many recent keyframes by how well "
              "their baseline and overlap constrain the reference's depth (the closest in time that move its "
              'pixels by parallax_full_px across that band), instead of the latest ones. 0 (or at most '
              'the window size): the latest keyframes.', min_value=0, max_value=32),
    ParamSpec('reject_degenerate_frames', True, 'Drop frames that carry no depth information (all black, '
              'saturated, flat or random noise): they neither update the filter nor produce an output.'),
    ParamSpec('confidence_calibration', '', 'A confidence calibration file (JSON, written by the calibrate tool from '
              'a recording with depth ground truth): maps the confidence to the probability, measured there, that '
              'the true depth is within x1.25 of the published one; applied before min_confidence, the depth is '
              'unchanged. It must have been fitted with the same weights, processing size and depth planes; a '
              'malformed or mismatched file stops the node at start. Empty: off.'),
    ParamSpec('min_confidence', 0.0, 'Depth with lower confidence is published as no estimate.',
              min_value=0.0, max_value=1.0),
    # --- transport ----------------------------------------------------------------------------------------
    ParamSpec('input_reliability', 'auto', 'QoS reliability of the subscriptions; auto: reliable while every '
              'publisher of the topic offers reliable, else best effort (which matches both kinds).',
              choices=('auto', 'best_effort', 'reliable'), scope='node'),
    ParamSpec('input_depth', 5, 'QoS history depth of the subscriptions.', min_value=1, max_value=1000, scope='node'),
    ParamSpec('image_transport', 'raw', 'How the colour image arrives, as an image_transport subscriber chooses: raw '
              '(sensor_msgs/Image on `image`) or compressed (sensor_msgs/CompressedImage, JPEG or PNG, on the image '
              "topic's child `image/compressed`, e.g. /camera/color/image_raw/compressed when `image` is remapped "
              'to /camera/color/image_raw; decoded with OpenCV on receipt: about 1 ms for a 640x480 JPEG, 7 ms for '
              'a PNG on one core of the 2-core CPU, benchmarks/image_decode.py). A payload that cannot be decoded '
              'is counted (faults.undecodable_image) and dropped.',
              choices=('raw', 'compressed'), scope='node'),
    ParamSpec('size_change_images', 3, "The image size changes only when the new size persists: an image of another "
              "size than the stream's is a stray, dropped on receipt (dropped.stray_image_size) without restarting "
              'the filter, until this many images in a row have one new size; the last of them is used and the '
              'filter restarts once. 1: every new size at once. Images under 2x2 pixels are always refused '
              '(dropped.image_too_small).', min_value=1, max_value=1000, scope='node'),
    ParamSpec('output_reliability', 'reliable', 'QoS reliability of the publishers.',
              choices=('best_effort', 'reliable'), scope='node'),
    ParamSpec('output_depth', 5, 'QoS history depth of the publishers.', min_value=1, max_value=1000, scope='node'),
    ParamSpec('diagnostics_period', 1.0, 'Seconds between /diagnostics messages.', min_value=0.05, max_value=60.0,
              scope='node'),
    # --- extra outputs and diagnostics ---------------------------------------------------------------------
    ParamSpec('publish_compressed_depth', False, 'Also publish depth/image/compressedDepth (sensor_msgs/'
              "CompressedImage, PNG as image_transport's compressedDepth plugin encodes it, in depth_encoding).",
              scope='node'),
    ParamSpec('points_decimation', 1, 'depth/points: every n-th pixel in each direction (organised cloud of '
              'ceil(H/n) x ceil(W/n); 640x480 at 4: 4.9 MB -> 0.31 MB per cloud).', min_value=1, max_value=16,
              scope='node'),
    ParamSpec('points_max_rate', 0.0, 'depth/points: at most this many clouds per second of image time (an output '
              "whose stamp is closer than 1/rate to the previous cloud's is skipped and counted). 0: every output.",
              min_value=0.0, max_value=1000.0, scope='node'),
    ParamSpec('expected_depth_rate', 0.0, 'Expected rate of depth/image (and rgb, confidence) in Hz: /diagnostics '
              'warns while the measured rate is below it by more than rate_tolerance. Keyframe outputs come at '
              'about a fifth of the camera rate at most. 0: no expectation.', min_value=0.0, max_value=1000.0,
              scope='node'),
    ParamSpec('expected_points_rate', 0.0, 'Expected rate of depth/points in Hz (as expected_depth_rate; only while '
              'someone subscribes). 0: no expectation.', min_value=0.0, max_value=1000.0, scope='node'),
    ParamSpec('rate_tolerance', 0.1, 'Share below an expected rate that is still fine (0.1: 10 %).',
              min_value=0.0, max_value=1.0, scope='node'),
    ParamSpec('rate_window', 10.0, 'Seconds over which output rates and the share of lost or faulty images are '
              'measured for /diagnostics.', min_value=1.0, max_value=600.0, scope='node'),
    ParamSpec('drop_warn_share', 0.1, 'Share of the images of the last rate_window lost in transport or rejected '
              'as faulty above which /diagnostics warns (images replaced while the node is busy do not count: '
              'they are the normal regime of a slow machine and are only reported).', min_value=0.0,
              max_value=1.0, scope='node'),
    ParamSpec('drop_error_share', 0.5, 'As drop_warn_share, for level ERROR.', min_value=0.0, max_value=1.0,
              scope='node'),
)


# Estimator settings that are not node parameters (library knobs with sensible defaults).
LIBRARY_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec('edge_filter_step', 4, 'Spacing (processing pixels) of the samples of the edge-aware refinement; its '
              'cost falls with the square of this.', min_value=1, max_value=32, scope='library'),
    ParamSpec('window_size', 5, 'Keyframes in a window (paper: 5; odd for the centered window).',
              min_value=2, max_value=31, scope='library'),
    ParamSpec('classical_downscale', 4, 'Volume resolution of the classical model: image size / this.',
              min_value=1, max_value=16, scope='library'),
    ParamSpec('min_coverage', 0.5, "Fraction of a ray's plane samples that must project into at least one "
              'source view for the pixel to get an estimate.', min_value=1e-6, max_value=1.0, scope='library'),
    ParamSpec('amp_dtype', 'bfloat16', 'Autocast dtype of the networks on CUDA, or none.',
              choices=('bfloat16', 'float16', 'none'), scope='library'),
)

SPEC_BY_NAME = {s.name: s for s in SPECS + LIBRARY_SPECS}
ESTIMATOR_SPECS = tuple(s for s in SPECS + LIBRARY_SPECS if s.scope in ('estimator', 'library'))
NODE_SPECS = tuple(s for s in SPECS if s.scope == 'node')


# Node parameters that may change while the node runs (`ros2 param set`); every other one needs a restart.
RUNTIME = frozenset({'min_confidence', 'damping', 'edge_filter_radius', 'edge_filter_sigma', 'depth_encoding',
                     'points_decimation', 'points_max_rate', 'expected_depth_rate', 'expected_points_rate',
                     'rate_tolerance', 'drop_warn_share', 'drop_error_share', 'odom_wait_timeout', 'frame_id'})


def extrinsic_source(setting: str, T_base_camera) -> str:
    """The camera mount's source in use, 'parameter' or 'tf', for the extrinsic_source `setting` (auto: the
    T_base_camera parameter when it is not the identity pose, else tf)."""
    if setting != 'auto':
        return setting
    pose = [float(v) for v in T_base_camera]
    identity = all(abs(v) <= 1e-9 for v in pose[:3]) and abs(abs(pose[6]) - 1.0) <= 1e-9
    return 'tf' if identity else 'parameter'


class ParameterError(ValueError):
    """A parameter value outside its type, choices or range."""


def check_changes(values: dict[str, Any], changes: dict[str, Any]) -> dict[str, Any]:
    """``values`` with ``changes`` applied, each checked against the table (and the relations); a setting outside
    ``RUNTIME`` is refused: it needs a restart."""
    out = dict(values)
    for name, value in changes.items():
        if name not in RUNTIME:
            raise ParameterError(f"parameter '{name}' cannot change while the node runs (restart it with the new "
                                 f"value); these can: {', '.join(sorted(RUNTIME))}")
        out[name] = check_value(spec(name), value)
    check_relations(out)
    return out


def spec(name: str) -> ParamSpec:
    try:
        return SPEC_BY_NAME[name]
    except KeyError:
        raise ParameterError(f"unknown setting '{name}'; known: {', '.join(sorted(SPEC_BY_NAME))}") from None


def default(name: str) -> Any:
    """The one default of a setting."""
    return spec(name).fresh_default()


def choices(name: str) -> tuple:
    """The choices of a setting (its one list)."""
    return tuple(spec(name).choices or ())


def defaults(specs: Iterable[ParamSpec] = SPECS) -> dict[str, Any]:
    """{name: default} of the node's parameters (or of ``specs``)."""
    return {s.name: s.fresh_default() for s in specs}


def expected_type(like: Any, length: int | None = None) -> str:
    """How the one error message names the type a setting takes (``like``: a value of that type)."""
    if isinstance(like, bool):
        return 'bool (true or false)'
    if isinstance(like, (list, tuple)):
        return f'a list of {length} numbers' if length else 'a list of numbers'
    return type(like).__name__


def type_error(name: str, expected: str, value: Any) -> ParameterError:
    """The one message for a value of the wrong type, shown by the node, the estimator and the tools alike:
    ``parameter 'NAME' must be TYPE, got VALUE``."""
    return ParameterError(f"parameter '{name}' must be {expected}, got {value!r}")


def check_value(s: ParamSpec, value: Any) -> Any:
    """``value`` checked against its spec (type, choices, range); ints promoted where a float is expected.
    Raises ParameterError with the one message every front end shows."""
    kind = s.kind
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if kind is str and isinstance(value, bool) and s.choices is not None and ('on' if value else 'off') in s.choices:
        # YAML 1.1 and the ROS 2 command line (-p pose_refinement:=off) read the words on / off as booleans
        value = 'on' if value else 'off'
    if kind is list:
        if not isinstance(value, (list, tuple)) or (s.length and len(value) != s.length):
            raise type_error(s.name, expected_type(s.default, s.length), value)
        try:
            value = [float(v) for v in value]
        except (TypeError, ValueError):
            raise type_error(s.name, expected_type(s.default, s.length), value) from None
        if not all(math.isfinite(v) for v in value):
            raise ParameterError(f"parameter '{s.name}' has a non-finite entry: {value!r}")
    elif not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
        raise type_error(s.name, expected_type(s.default), value)
    if s.choices is not None and value not in s.choices:
        raise ParameterError(f"parameter '{s.name}' = {value!r} is not one of {list(s.choices)}")
    if kind in (int, float):
        if not math.isfinite(value):
            raise ParameterError(f"parameter '{s.name}' = {value!r} is not finite")
        if s.min_value is not None and value < s.min_value:
            raise ParameterError(f"parameter '{s.name}' = {value!r} is below its minimum {s.min_value}")
        if s.max_value is not None and value > s.max_value:
            raise ParameterError(f"parameter '{s.name}' = {value!r} is above its maximum {s.max_value}")
    return value


def check_relations(values: dict[str, Any]) -> None:
    """The rules between settings, for whichever of them ``values`` holds."""
    if 'd_min' in values and 'd_max' in values and values['d_min'] >= values['d_max']:
        raise ParameterError(f"d_min ({values['d_min']}) must be below d_max ({values['d_max']})")
    if values.get('camera_info_source') == 'parameters' and min(values['fx'], values['fy']) <= 0.0:
        raise ParameterError("camera_info_source is 'parameters' but fx/fy are not set (> 0)")
    if 'T_base_camera' in values:
        q = values['T_base_camera'][3:]
        if abs(math.sqrt(sum(c * c for c in q)) - 1.0) > 1e-3:
            raise ParameterError(f'T_base_camera quaternion {q} is not unit length')
    if 'window_size' in values and 'window_mode' in values and values['window_mode'] == 'centered' \
            and values['window_size'] % 2 != 1:
        raise ParameterError(f"window_size {values['window_size']} does not fit window_mode 'centered' (odd)")


def validate(values: dict[str, Any], specs: Sequence[ParamSpec] = SPECS) -> dict[str, Any]:
    """Check every setting of ``specs`` (all must be present) and the relations between them; return the values
    with ints promoted where a float is expected. Raises ParameterError naming the first offending setting."""
    out = dict(values)
    for s in specs:
        if s.name not in values:
            raise ParameterError(f"parameter '{s.name}' is missing")
        out[s.name] = check_value(s, values[s.name])
    check_relations(out)
    return out


# ------------------------------------------------------------------------------------------------------
# config classes built from the table
# ------------------------------------------------------------------------------------------------------

def make_config_class(name: str, specs: Sequence[ParamSpec], doc: str, namespace: dict | None = None) -> type:
    """A dataclass with one field per spec (default from the table) plus ``validate()`` (table checks and
    relations; returns self), ``from_params(values)`` (the fields named in ``values``, others default; validated)
    and ``as_dict()``. ``namespace``: extra methods / properties."""

    def validate_(self):
        values = validate({s.name: getattr(self, s.name) for s in specs}, specs)
        for k, v in values.items():
            setattr(self, k, v)
        return self

    @classmethod
    def from_params(cls, values: dict[str, Any]):
        names = {s.name for s in specs}
        return cls(**{k: v for k, v in values.items() if k in names}).validate()

    def as_dict(self) -> dict[str, Any]:
        return {s.name: getattr(self, s.name) for s in specs}

    fields = [(s.name, s.kind, dataclasses.field(default_factory=s.fresh_default) if s.kind is list
               else dataclasses.field(default=s.default)) for s in specs]
    ns = {'validate': validate_, 'from_params': from_params, 'as_dict': as_dict, 'SPECS': tuple(specs),
          '__doc__': doc}
    ns.update(namespace or {})
    return dataclasses.make_dataclass(name, fields, namespace=ns)


NodeConfig = make_config_class('NodeConfig', NODE_SPECS, """The node's own settings (topics, QoS, encodings,
odometry buffer, camera intrinsics): the ``node`` scope of the table, one field per setting.""")
NodeConfig.__module__ = __name__


# ------------------------------------------------------------------------------------------------------
# key=value parsing (the tools' --config / --param)
# ------------------------------------------------------------------------------------------------------

def parse_value(text: str, like: Any, name: str = 'value') -> Any:
    """Parse ``text`` as the type of ``like`` (bool: true/false/1/0/yes/no/on/off; list: comma-separated numbers,
    brackets optional). Text that is not of that type raises :func:`type_error` naming the setting ``name``."""
    try:
        if isinstance(like, bool):
            low = text.strip().lower()
            if low in ('true', '1', 'yes', 'on'):
                return True
            if low in ('false', '0', 'no', 'off'):
                return False
            raise ValueError(text)
        if isinstance(like, int):
            return int(text)
        if isinstance(like, float):
            return float(text)
        if isinstance(like, (list, tuple)):
            return [float(x) for x in text.strip().strip('[]').split(',') if x.strip()]
    except ValueError:
        length = SPEC_BY_NAME[name].length if name in SPEC_BY_NAME else None
        raise type_error(name, expected_type(like, length), text) from None
    return text


def split_assignment(item: str, sep: str = '=') -> tuple[str, str]:
    """``'key=value'`` (or ``'key:=value'``) -> (key, value); ValueError when there is no separator."""
    for s in (':=', sep):
        if s in item:
            key, value = item.split(s, 1)
            return key.strip(), value.strip()
    raise ValueError(f'expected key=value (KEY=VALUE or KEY:=VALUE), got {item!r}')


def parse_assignments(items: Iterable[str], known: dict[str, Any] | None = None) -> dict[str, Any]:
    """``['filter_mode=global', 'damping=0.5']`` -> typed dict. ``known``: {key: value of its type}; default
    every setting of the table. Unknown keys raise ValueError."""
    known = {n: s.default for n, s in SPEC_BY_NAME.items()} if known is None else known
    out: dict[str, Any] = {}
    for item in items:
        key, value = split_assignment(item)
        if key not in known:
            raise ValueError(f'unknown configuration key {key!r}; known: {", ".join(sorted(known))}')
        out[key] = parse_value(value, known[key], key)
    return out


# ------------------------------------------------------------------------------------------------------
# the documented YAML
# ------------------------------------------------------------------------------------------------------

def _yaml_scalar(value: Any) -> str:
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, str):
        return '"' + value.replace('\\', '\\\\').replace('"', '\\"') + '"'
    if isinstance(value, list):
        return '[' + ', '.join(_yaml_scalar(v) for v in value) + ']'
    return repr(value)


def _constraint(s: ParamSpec) -> str:
    if s.choices:
        return ' (one of ' + ', '.join(map(str, s.choices)) + ')'
    if s.min_value is not None or s.max_value is not None:
        lo = '-inf' if s.min_value is None else format(s.min_value, 'g')
        hi = 'inf' if s.max_value is None else format(s.max_value, 'g')
        return f' (range [{lo}, {hi}])'
    return ''


def yaml_text() -> str:
    """config/dpv_sensor.yaml as generated from the table: every node parameter with its default, keyed
    ``/**:`` so that the file applies to the node under any name and namespace."""
    lines = ['# dpv_sensor node parameters (ros2 run dpv_sensor node --ros-args --params-file config/dpv_sensor.yaml).',
             '# Every parameter the node declares is listed here with its default; ranges are checked at start.',
             '# Generated from dpv_sensor/params.py (python -m dpv_sensor.params > config/dpv_sensor.yaml).',
             '# Keyed /** so that it applies to the node in any namespace and under any node name.',
             *textwrap.wrap('Changeable while the node runs (ros2 param set): ' + ', '.join(sorted(RUNTIME)) +
                            '. Every other parameter needs a restart.', width=112, initial_indent='# ',
                            subsequent_indent='# ', break_on_hyphens=False),
             '/**:', '  ros__parameters:']
    for s in SPECS:
        text = s.description + _constraint(s)
        lines += textwrap.wrap(text, width=112, initial_indent='    # ', subsequent_indent='    # ',
                               break_on_hyphens=False)
        lines.append(f'    {s.name}: {_yaml_scalar(s.default)}')
    return '\n'.join(lines) + '\n'


if __name__ == '__main__':
    print(yaml_text(), end='')
