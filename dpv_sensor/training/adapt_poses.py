"""The camera poses an adaptation run warps with: the recording's odometry as the node would use it.

The node does not take a keyframe's odometry pose as it is: its window refiner (``pose_refinement: window``,
:class:`~dpv_sensor.stream.window_refiner.WindowPoseRefiner`) corrects each keyframe against its neighbours with
the images' own evidence before the networks see it. :func:`node_keyframe_poses` runs the recording once through
the node's :class:`~dpv_sensor.stream.pipeline.Pipeline` at its defaults (the base weights, the processing size,
no depth read) and returns the keyframes the node picked with the poses it used for them, so the adaptation's
photometric losses warp with what the node will warp with. The frames are pushed at the processing size, as the
recording is held; the refiner's flow therefore matches at that size too.

A keyframe that never left the node's window (the last ones of a centred window) keeps its odometry pose and is
counted.
"""
from __future__ import annotations

import dataclasses
from typing import Dict, List, Optional

import numpy as np

__all__ = ['POSE_SOURCES', 'NodePoses', 'node_keyframe_poses']

#: where an adaptation's poses come from: the node's refined keyframe poses, or the odometry as recorded
POSE_SOURCES = ('window', 'odometry')


@dataclasses.dataclass
class NodePoses:
    """keyframes: frame indices the node picked, in order; poses: every frame's pose, the keyframes' as the node
    used them (the others the odometry's); stats: counts for the report (keyframes, refined, kept as recorded,
    the median and largest change of a keyframe step's rotation in degrees, the refiner's factor decisions)."""
    keyframes: List[int]
    poses: List[np.ndarray]
    stats: Dict


def _step_rotation_change_deg(a: List[np.ndarray], b: List[np.ndarray], keys: List[int]) -> np.ndarray:
    """Per consecutive keyframe pair: the angle (deg) between its relative pose's rotation in ``a`` and in ``b``."""
    from dpv_sensor.core.pose_math import relative_pose_error_np
    return np.asarray([relative_pose_error_np(np.linalg.inv(a[i]) @ a[j], np.linalg.inv(b[i]) @ b[j])[1]
                       for i, j in zip(keys[:-1], keys[1:])], np.float64)


def node_keyframe_poses(sequence, model, width: int, height: int, overrides: Optional[Dict] = None,
                        progress: bool = False) -> NodePoses:
    """Run ``sequence`` (images at ``width`` x ``height``, odometry poses, no depth) through the node's pipeline at
    its defaults with ``model`` (the base weights; not changed) and return the node's keyframes and their poses."""
    import torch

    from dpv_sensor.evaluation.runner import build_config
    from dpv_sensor.stream.frame import Frame
    from dpv_sensor.stream.pipeline import Pipeline
    config, _ = build_config(dict({'processing_width': width, 'processing_height': height}, **(overrides or {})))
    was = model.training
    model.eval()
    pipe = Pipeline(config, model=model)
    odometry = [np.asarray(sequence.pose(i), np.float64) for i in range(len(sequence))]
    poses = [T.copy() for T in odometry]
    K = np.asarray(sequence.K, np.float64)
    index_of: Dict[float, int] = {}
    keyframes, refined = [], set()
    frames = range(len(sequence))
    if progress:
        from tqdm import tqdm
        frames = tqdm(frames, desc='node poses', unit='frame', leave=False)
    try:
        with torch.no_grad():
            for i in frames:
                stamp = float(sequence.stamp(i))
                index_of[stamp] = i
                result = pipe.push(Frame(stamp=stamp, image=sequence.image(i), K_33=K, T_world_cam_44=odometry[i]))
                if result.is_keyframe:
                    keyframes.append(i)
                out = result.output
                if out is not None and out.is_keyframe and out.T_world_cam_44 is not None:
                    j = index_of[out.stamp]
                    poses[j] = np.asarray(out.T_world_cam_44, np.float64).copy()
                    refined.add(j)
    finally:
        model.train(was)
    change = _step_rotation_change_deg(odometry, poses, keyframes) if len(keyframes) > 1 else np.zeros(0)
    status = pipe.status
    stats = {'keyframes': len(keyframes), 'refined': len(refined), 'kept_as_recorded': len(keyframes) - len(refined),
             'step_rotation_change_deg': {'median': float(np.median(change)) if change.size else 0.0,
                                          'max': float(change.max()) if change.size else 0.0},
             'refiner_factors': dict(getattr(status, 'pose_refinement_factors', None) or {}),
             'refiner_windows': dict(getattr(status, 'pose_refinement_gate', None) or {})}
    return NodePoses(keyframes, poses, stats)
