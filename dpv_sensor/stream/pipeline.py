"""The sensor pipeline below the node: the pose source and the estimator, as the node and the offline tools run it.

No ROS here. ``Pipeline(config).push(frame) -> PushResult`` is what the node calls per image (after converting the
message and looking the odometry pose up) and what
``evaluation.runner.run_sequence`` (the one offline runner) calls per frame of a
sequence, so odometry-free mode, pose refinement and their tracking-loss rules behave the same online and offline.

The pose source (:class:`PoseSource`), built from the :class:`~dpv_sensor.stream.estimator.EstimatorConfig`:

* ``odometry='topic'``: the frame's pose is the odometry pose the caller gives (``Frame.T_world_cam_44``);
* ``odometry='none'``: :class:`~dpv_sensor.stream.visual_odometry.VisualOdometry` tracks every frame against the
  latest keyframe depth; when it loses tracking the frame is dropped (``PushResult.drop``) and the pipeline
  restarts;
* ``pose_refinement='window'``: :class:`~dpv_sensor.stream.window_refiner.WindowPoseRefiner`, with the sigmas of
  the config (``odom_sigma_rot_deg``, ``odom_sigma_trans_m``, ``odom_sigma_trans_rel``), refines the keyframe poses
  of each window inside the estimator. A refinement that fails (an alignment that does not converge, too few usable
  alignments, a refined pose implausibly far from the odometry) keeps the odometry poses for that keyframe when
  the odometry comes from a topic (counted as a fallback, the filter goes on); with visual odometry it is a
  tracking loss and restarts the filter.

The mount check (``mount_check``, :mod:`dpv_sensor.stream.mount_check`) watches the same stream: every pushed frame's
pose and every refinement window's matches, to estimate the camera mount's rotation and the time offset against the
odometry (odometry from a topic with the refinement window only).

The stream-continuity rules are in ``dpv_sensor.stream.continuity`` (applied by the estimator on every pushed frame).
"""
from __future__ import annotations

import collections
import dataclasses
from dataclasses import dataclass
from typing import Optional

import numpy as np

from dpv_sensor.stream.estimator import Estimator, EstimatorConfig, EstimatorStatus
from dpv_sensor.stream.frame import DepthOutput, Frame
from dpv_sensor.stream.mount_check import MountCheck, MountCheckConfig

__all__ = ['PoseSource', 'Pipeline', 'PushResult', 'VO_LOST', 'DEGENERATE']

VO_LOST = 'visual_odometry_lost'
DEGENERATE = 'degenerate_image'    # the estimator refused the frame (reject_degenerate_frames, image_quality)


@dataclass
class PushResult:
    """What one pushed frame gave: the output that became ready (or None); ``drop`` / ``detail``: why the frame
    was dropped before the estimator (a counter name and its message); ``is_keyframe``: the frame became one."""
    output: Optional[DepthOutput] = None
    drop: Optional[str] = None
    detail: Optional[str] = None
    is_keyframe: bool = False


class PoseSource:
    """Odometry, the refinement window, visual odometry and their tracking loss (see the module docstring)."""

    def __init__(self, config: EstimatorConfig, pose_refiner=None):
        self.config = config
        self.refiner = pose_refiner
        if self.refiner is None and config.pose_refinement == 'window':
            from dpv_sensor.stream.window_refiner import PoseRefinerConfig, WindowPoseRefiner
            self.refiner = WindowPoseRefiner(PoseRefinerConfig.from_params(config.as_dict()))
        self.visual_odometry = None
        if config.odometry == 'none':
            from dpv_sensor.stream.visual_odometry import VisualOdometry
            self.visual_odometry = VisualOdometry()

    def frame_pose(self, frame: Frame):
        """(T_world_cam or None, lost reason or None) of a frame: the given pose, or visual odometry's."""
        if self.visual_odometry is None:
            return frame.T_world_cam_44, None
        vo = self.visual_odometry.track(frame.image, frame.K_33, float(frame.stamp))
        if not vo.tracking_ok:
            return None, str(vo.reason)
        return vo.T_world_cam_44, None

    def keyframe_output(self, out: DepthOutput, image: Optional[np.ndarray], K_in_33) -> None:
        """A keyframe's depth became ready: visual odometry tracks against it from now on."""
        if self.visual_odometry is None or image is None or not out.is_keyframe:
            return
        h, w = out.depth_hw.shape
        K_depth = None if (h, w) == image.shape[:2] else np.asarray(out.K_33, dtype=np.float64)
        self.visual_odometry.set_keyframe(image, K_in_33, out.T_world_cam_44, out.depth_hw, out.confidence_hw,
                                          K_depth_33=K_depth, stamp=float(out.stamp))

    def reset(self) -> None:
        if self.refiner is not None and callable(getattr(self.refiner, 'reset', None)):
            self.refiner.reset()
        if self.visual_odometry is not None:
            self.visual_odometry.reset()

    @property
    def tracking(self) -> Optional[str]:
        """'ok', 'odometry fallback: <reason>' (odometry from a topic) or 'lost: <reason>' of the refiner's last
        window, or None without a refiner."""
        if self.refiner is None:
            return None
        last = getattr(self.refiner, 'last_result', None)
        if last is None or last.tracking_ok:
            return 'ok'
        if self.config.odometry == 'topic':
            return f'odometry fallback: {last.reason}'
        return f'lost: {last.reason}'


class Pipeline:
    """Pose source + estimator (+ the mount check). ``model`` / ``pose_refiner`` / ``logger``: as for
    :class:`Estimator`; ``mount_text``: names the mount to set for a mount-check fit in its WARN (the node's)."""

    def __init__(self, config: Optional[EstimatorConfig] = None, *, model=None, pose_refiner=None, logger=None,
                 mount_text=None):
        config = (config or EstimatorConfig()).validate()
        self.pose_source = PoseSource(config, pose_refiner)
        self.estimator = Estimator(config, model=model, pose_refiner=self.pose_source.refiner, logger=logger)
        self.config = self.estimator.config
        self.mount_check = None
        if config.mount_check and config.odometry == 'topic' and self.pose_source.refiner is not None:
            self.mount_check = MountCheck(MountCheckConfig(), logger=logger, mount_text=mount_text)
        # keyframe images and intrinsics by stamp: a (centered) keyframe's output comes later than its frame
        self._keyframe_images: collections.OrderedDict = collections.OrderedDict()

    @property
    def status(self) -> EstimatorStatus:
        """The estimator's status with the pose source's tracking (``pose_refinement_tracking``) and the mount
        check's (``mount_check``)."""
        mount = {} if self.mount_check is None else self.mount_check.status.as_dict()
        return dataclasses.replace(self.estimator.status, pose_refinement_tracking=self.pose_source.tracking,
                                   mount_check=mount)

    def push(self, frame: Frame) -> PushResult:
        T, lost = self.pose_source.frame_pose(frame)
        if lost is not None:
            self.reset(f'visual odometry lost: {lost}')
            return PushResult(drop=VO_LOST, detail=lost)
        if T is not frame.T_world_cam_44:
            frame = Frame(stamp=frame.stamp, image=frame.image, K_33=frame.K_33, T_world_cam_44=T,
                          frame_id=frame.frame_id, sensor_gap_s=frame.sensor_gap_s)
        keyframes_before, degenerate_before = self.estimator.counts
        out = self.estimator.push(frame)
        keyframes_after, degenerate_after = self.estimator.counts
        if degenerate_after > degenerate_before:
            return PushResult(output=out, drop=DEGENERATE, detail=str(self.estimator.status.last_degenerate_reason))
        is_keyframe = keyframes_after > keyframes_before
        if self.mount_check is not None:
            self.mount_check.observe_frame(float(frame.stamp), T)
            if is_keyframe:
                self.mount_check.observe_window(getattr(self.pose_source.refiner, 'last_result', None))
        if is_keyframe and self.pose_source.visual_odometry is not None:
            self._keyframe_images[float(frame.stamp)] = (frame.image, np.asarray(frame.K_33, dtype=np.float64))
            while len(self._keyframe_images) > 2 * int(self.config.window_size) + 6:
                self._keyframe_images.popitem(last=False)
        if out is not None and out.is_keyframe and self.pose_source.visual_odometry is not None:
            image, K_in = self._keyframe_images.get(float(out.stamp), (None, None))
            self.pose_source.keyframe_output(out, image, K_in)
        return PushResult(output=out, is_keyframe=is_keyframe)

    def apply_settings(self, changes: dict) -> None:
        """Settings changed while running (the estimator-scope ones of params.RUNTIME, read at use: min_confidence,
        damping, the edge filter): set on the estimator's config, and the damping on its running filter."""
        for name, value in changes.items():
            if hasattr(self.estimator.config, name):
                setattr(self.estimator.config, name, value)
        if 'damping' in changes and getattr(self.estimator, 'filter', None) is not None:
            self.estimator.filter.damping = float(changes['damping'])

    def reset(self, reason: str) -> None:
        """Restart the estimator (window, keyframes, filter) and the pose source."""
        self.estimator.reset(reason)
        self.pose_source.reset()
        self._keyframe_images.clear()
