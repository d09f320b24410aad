"""The one offline runner: a posed RGB-D sequence pushed frame by frame through the
:class:`~dpv_sensor.stream.pipeline.Pipeline` the node runs, each keyframe output kept as a :class:`KeyframeRecord`.

``evaluate``, the benchmarks and the training's stream validation all run sequences through :func:`run_sequence`
and score the records with :func:`dpv_sensor.evaluation.scoring.score_records`. Here too: the evaluation options
(:class:`EvalOptions`), the configuration from the settings table (:func:`build_config`, :func:`parse_overrides`)
and the sequence preparation (load, cut, resize, the pose source ``gt`` or ``noisy``).
"""
from __future__ import annotations

import pathlib
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Dict, Iterable, List, Optional, Tuple

import cv2
import numpy as np

from dpv_sensor import params as P

if TYPE_CHECKING:
    from dpv_sensor.stream.estimator_config import EstimatorStatus

__all__ = ['POSE_SOURCES', 'EVAL_KEYS', 'EvalOptions', 'KeyframeRecord', 'known_keys', 'parse_overrides',
           'build_config', 'load_sequence', 'load_source', 'prepare_sequence', 'resize_nearest', 'resize_image',
           'input_poses', 'run_sequence', 'depth_limits']

POSE_SOURCES = ('gt', 'noisy')
# Keys a configuration may carry that are evaluation settings, not estimator parameters.
EVAL_KEYS = ('pose_source',)

# ----------------------------------------------------------------------------------------------
# Options and records
# ----------------------------------------------------------------------------------------------

@dataclass
class EvalOptions:
    """How a sequence is evaluated (not estimator parameters).

    min_depth / max_depth: GT range scored (None: the estimator's d_min / d_max). width / height: resize
    the input sequence first (both or neither). start / max_frames: the frames used. pose_source: 'gt' or
    'noisy' (``pose_noise`` = (relative translation noise per step, rotation noise deg per step), seeded
    by ``seed``). montage_frames: rows of the montage. occlusion_tol: relative GT-depth agreement that
    counts a pixel as visible in both frames for temporal consistency. progress: tqdm bars.
    consumer_odometry: add :func:`consumer_odometry` (Open3D RGB-D odometry on predicted vs GT depth) to the
    summary.
    """
    min_depth: Optional[float] = None
    max_depth: Optional[float] = None
    width: Optional[int] = None
    height: Optional[int] = None
    start: int = 0
    max_frames: Optional[int] = None
    pose_source: str = 'gt'
    pose_noise: Tuple[float, float] = (0.03, 0.5)
    seed: int = 0
    montage_frames: int = 4
    occlusion_tol: float = 0.05
    progress: bool = True
    consumer_odometry: bool = True

    def validate(self) -> 'EvalOptions':
        if self.pose_source not in POSE_SOURCES:
            raise ValueError(f'pose_source {self.pose_source!r} is not one of {list(POSE_SOURCES)}')
        if (self.width is None) != (self.height is None):
            raise ValueError('give both width and height to resize, or neither')
        if self.min_depth is not None and self.max_depth is not None and self.min_depth >= self.max_depth:
            raise ValueError(f'min_depth {self.min_depth} must be below max_depth {self.max_depth}')
        return self


@dataclass
class KeyframeRecord:
    """One scored output.

    depth_hw: float32 metres, NaN = no estimate; confidence_hw: [0, 1] or None; K_33: intrinsics of the
    depth map's size; T_world_cam_44: the pose the estimator used (None when unknown, e.g. from a bag);
    gt_depth_hw: GT at the depth map's size (0 = invalid); gt_T_world_cam_44: GT pose; image_hw3: colour
    at the depth map's size (for montages) or None; reset_reason: set when the filter restarted here.
    """
    index: int
    stamp: float
    depth_hw: np.ndarray
    confidence_hw: Optional[np.ndarray]
    K_33: np.ndarray
    gt_depth_hw: np.ndarray
    gt_T_world_cam_44: Optional[np.ndarray]
    T_world_cam_44: Optional[np.ndarray] = None
    image_hw3: Optional[np.ndarray] = None
    reset_reason: Optional[str] = None
    time_ms: float = float('nan')
    features: Optional[Dict[str, np.ndarray]] = None


# ----------------------------------------------------------------------------------------------
# Configuration
# ----------------------------------------------------------------------------------------------


def known_keys() -> Dict[str, Any]:
    """Every key a configuration may set, with a value of its type: every setting of the table (node
    parameters and the estimator's library settings) and the evaluation keys."""
    keys: Dict[str, Any] = {name: spec.default for name, spec in P.SPEC_BY_NAME.items()}
    keys['pose_source'] = 'gt'
    return keys


def parse_overrides(items: Iterable[str]) -> Dict[str, Any]:
    """``['filter_mode=global', 'damping=0.5']`` -> typed dict; unknown keys raise ValueError."""
    return P.parse_assignments(items, known_keys())


def build_config(overrides: Optional[Dict[str, Any]] = None):
    """(EstimatorConfig, validated parameter dict) from the node defaults plus ``overrides``.

    Evaluation keys (``pose_source``) are ignored here. Raises ``params.ParameterError`` / ValueError.
    """
    from dpv_sensor.stream.estimator import EstimatorConfig
    values = P.defaults(P.SPECS + P.LIBRARY_SPECS)
    for k, v in (overrides or {}).items():
        if k not in EVAL_KEYS:
            values[k] = v
    values = P.validate(values, P.SPECS + P.LIBRARY_SPECS)
    return EstimatorConfig.from_params(values), values


# ----------------------------------------------------------------------------------------------
# Sequences
# ----------------------------------------------------------------------------------------------

def load_sequence(seq) -> Any:
    """A :class:`~dpv_sensor.data.sequence.Sequence` from a folder path; other objects pass through."""
    if isinstance(seq, (str, pathlib.Path)):
        from dpv_sensor.data.sequence import Sequence
        return Sequence(seq)
    return seq


def load_source(text: str, width: Optional[int], height: Optional[int]):
    """A sequence folder path, or ``synthetic:SEED[:FRAMES]`` rendered in memory."""
    if text.startswith('synthetic:'):
        from dpv_sensor.data.synthetic import render_sequence
        parts = text.split(':')
        seed = int(parts[1])
        frames = int(parts[2]) if len(parts) > 2 else 60
        return render_sequence(seed, frames, width=width or 320, height=height or 240)
    path = pathlib.Path(text)
    if not path.is_dir():
        raise ValueError(f'{path} is not a sequence folder')
    return path


def prepare_sequence(seq, options: EvalOptions):
    """Load, cut to ``start`` / ``max_frames`` and resize as the options say."""
    seq = load_sequence(seq)
    n = len(seq)
    stop = n if options.max_frames is None else min(n, options.start + int(options.max_frames))
    if options.start or stop < n:
        if not hasattr(seq, 'subset'):
            raise ValueError('start / max_frames need a Sequence (with subset())')
        seq = seq.subset(range(options.start, stop))
    if options.width is not None:
        seq = seq.resized(int(options.width), int(options.height))
    return seq


def resize_nearest(a: np.ndarray, hw: Tuple[int, int]) -> np.ndarray:
    if a.shape[:2] == tuple(hw):
        return a
    return cv2.resize(a, (int(hw[1]), int(hw[0])), interpolation=cv2.INTER_NEAREST_EXACT)


def resize_image(img: np.ndarray, hw: Tuple[int, int]) -> np.ndarray:
    if img.shape[:2] == tuple(hw):
        return img
    shrink = hw[0] <= img.shape[0] and hw[1] <= img.shape[1]
    return cv2.resize(img, (int(hw[1]), int(hw[0])), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)


def input_poses(seq, options: EvalOptions) -> List[np.ndarray]:
    """The poses the estimator is fed: GT, or (``pose_source='noisy'``) an odometry-like corruption of them."""
    gt = [np.asarray(seq.pose(i), np.float64) for i in range(len(seq))]
    if options.pose_source == 'gt':
        return gt
    from dpv_sensor.data.trajectory import corrupt_trajectory
    return corrupt_trajectory(gt, trans_noise_rel=float(options.pose_noise[0]),
                              rot_noise_deg=float(options.pose_noise[1]), seed=options.seed)


# ----------------------------------------------------------------------------------------------
# Running the pipeline
# ----------------------------------------------------------------------------------------------

def run_sequence(seq, config, options: Optional[EvalOptions] = None, *, model=None, pose_refiner=None,
                 keep_images: bool = True, poses: Optional[List[np.ndarray]] = None,
                 pose_variance: Optional[np.ndarray] = None, twist_variance: Optional[np.ndarray] = None,
                 features: bool = False) -> Tuple[List[KeyframeRecord], EstimatorStatus]:
    """Push the sequence (prepared as ``options`` say) frame by frame through a :class:`Pipeline`, the node's code
    path; return (keyframe records, the pipeline's :class:`EstimatorStatus`). The one offline runner.

    config: an ``EstimatorConfig``; the pose source comes from it (``pipeline.PoseSource``): with
    ``pose_refinement='window'`` and no ``pose_refiner`` given, a WindowPoseRefiner with the config's sigmas,
    with ``odometry='none'`` visual odometry instead of the sequence's poses. ``model``: a DPVNet to use
    instead of loading weights (see ``Estimator``). ``poses``: the odometry pose of every frame in place of the
    options' pose source; ``pose_variance``: one row per frame (position, rotation variance per axis) published as
    the frames' pose covariance, as ``data.rosbag_io.write_sequence_bag`` writes it into a bag's odometry;
    ``twist_variance``: one row per frame (linear, angular variance per axis and second) published as the frames' twist
    covariance, likewise. ``features``: the records carry each keyframe's confidence cues
    (``stream.confidence_features``) at the depth map's size.
    """
    from dpv_sensor.data.rosbag_io import COVARIANCE_FLOOR_SIGMA
    from dpv_sensor.stream.frame import Frame
    from dpv_sensor.stream.pipeline import Pipeline
    options = (options or EvalOptions()).validate()
    seq = prepare_sequence(seq, options)
    pipe = Pipeline(config, model=model, pose_refiner=pose_refiner)
    pipe.estimator.collect_features = features
    poses_in = input_poses(seq, options) if poses is None else poses
    floor = COVARIANCE_FLOOR_SIGMA ** 2
    K = np.asarray(seq.K, np.float64)
    index_of: Dict[float, int] = {}
    records: List[KeyframeRecord] = []
    iterator: Iterable[int] = range(len(seq))
    if options.progress:
        from tqdm import tqdm
        iterator = tqdm(iterator, desc='estimating', unit='frame', leave=False)
    for i in iterator:
        stamp = float(seq.stamp(i))
        index_of[stamp] = i
        cov = None if pose_variance is None else np.diag([max(float(pose_variance[i][0]), floor)] * 3
                                                         + [max(float(pose_variance[i][1]), floor)] * 3)
        twist = None if twist_variance is None else np.diag([float(twist_variance[i][0])] * 3
                                                            + [float(twist_variance[i][1])] * 3)
        out = pipe.push(Frame(stamp=stamp, image=seq.image(i), K_33=K, T_world_cam_44=poses_in[i],
                              frame_id='camera', pose_covariance_66=cov, twist_covariance_66=twist)).output
        if out is None or not out.is_keyframe:
            continue
        j = index_of[out.stamp]
        hw = out.depth_hw.shape
        gt = resize_nearest(np.asarray(seq.depth(j), np.float32), hw)
        image = resize_image(seq.image(j), hw) if keep_images else None
        records.append(KeyframeRecord(
            index=j, stamp=out.stamp, depth_hw=out.depth_hw, confidence_hw=out.confidence_hw,
            K_33=np.asarray(out.K_33, np.float64), gt_depth_hw=gt, gt_T_world_cam_44=np.asarray(seq.pose(j)),
            T_world_cam_44=None if out.T_world_cam_44 is None else np.asarray(out.T_world_cam_44),
            image_hw3=image, reset_reason=out.reset_reason,
            time_ms=float(out.timings_ms.get('total', float('nan'))),
            features=None if out.features is None else {k: resize_nearest(v, hw) for k, v in out.features.items()}))
    return records, pipe.status


def status_json(status: EstimatorStatus) -> Dict[str, Any]:
    """The estimator status as ``summary.json`` holds it: its fields (``EstimatorStatus.as_dict``) and the ends of
    its depth range (d_min, d_max)."""
    out = status.as_dict()
    out['depth_range'] = list(status.depth_range)
    out['d_min'], out['d_max'] = (float(d) for d in status.depth_range)
    return out


def depth_limits(options: EvalOptions, status: EstimatorStatus) -> Tuple[Optional[float], Optional[float]]:
    """(min, max) GT depth that is scored: the options' limits, else the estimator's depth range."""
    lo = options.min_depth if options.min_depth is not None else float(status.depth_range[0])
    hi = options.max_depth if options.max_depth is not None else float(status.depth_range[1])
    return lo, hi

