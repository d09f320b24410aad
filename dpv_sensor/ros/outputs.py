"""The node's outputs: the publishers (depth, colour and confidence images each with its camera_info, the
compressed depth, the point cloud, the pose, TF), the headers of recent input frames (every output carries exactly
the header of the input image it belongs to; a centered window publishes a keyframe's output two keyframes later),
and the output counters /diagnostics reports (rates, latency, stamp age, output resets).

Every camera_info is the same: K of the output size (the input K scaled in float64, rectified when the node
rectifies), D zero. depth/points is computed only while subscribed (points_decimation, points_max_rate).
"""
from __future__ import annotations

import collections
import dataclasses
import time
from dataclasses import dataclass

import cv2
import numpy as np
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2

from dpv_sensor.ros import msgs as M
from dpv_sensor.ros import pose_msgs as PM
from dpv_sensor.ros import cloud_msgs as C
from dpv_sensor.ros import compressed_depth as CD
from dpv_sensor.ros import qos
from dpv_sensor.ros.fault_kinds import MISSING_RGB, OUTPUT_K_MISMATCH, PUBLISH_ERROR, UNKNOWN_OUTPUT
from dpv_sensor.ros.node_support import RateMeter, plausible_age_ms

NS = 1_000_000_000


@dataclass
class FrameMeta:
    """What an output needs of the input frame it belongs to."""
    stamp_ns: int        # the image's header stamp, exactly
    frame_id: str
    rgb: object          # HxWx3 uint8 (kept for keyframes: the point cloud colours, visual odometry)
    K_in: object         # intrinsics of the input image (float64)
    in_w: int
    in_h: int
    receipt_mono: float
    receipt_ns: int


class NodeOutputs:
    """Publishers and the output counters. `node`: the rclpy node (its ``settings`` are read at use)."""

    def __init__(self, node, faults, qos_events: qos.QosEvents, T_base_camera_44):
        """`T_base_camera_44`: the mount the TF output publishes (publish_tf); None when it comes from TF."""
        s = node.settings.node
        self.node = node
        self.faults = faults
        self._qos_events = qos_events
        # DDS-matched subscribers per output topic (publication-matched events of the writer): a reliable volatile
        # writer sends only to the readers it has matched, so a subscriber the graph lists may still miss outputs
        self.matched: dict[str, int] = {}
        out_qos = qos.profile(s.output_reliability, s.output_depth)
        pub = self._publisher
        self.depth = pub(Image, 'depth/image', out_qos)
        self.depth_info = pub(CameraInfo, 'depth/camera_info', out_qos)
        # the colour image each depth was computed for, with the same header, size and K (rtabmap's rgbd_sync and
        # depth_image_proc pair them by exact stamp; the camera's own colour stream has no image at most stamps
        # of the keyframe outputs)
        self.rgb = pub(Image, 'rgb/image', out_qos)
        self.rgb_info = pub(CameraInfo, 'rgb/camera_info', out_qos)
        self.conf = pub(Image, 'confidence/image', out_qos)
        self.conf_info = pub(CameraInfo, 'confidence/camera_info', out_qos)
        self.compressed = None
        if s.publish_compressed_depth:
            # image_transport's topic name for the compressedDepth transport of depth/image
            self.compressed = pub(CompressedImage, 'depth/image/compressedDepth', out_qos)
        self.points = pub(PointCloud2, 'depth/points', out_qos)
        self.pose = None
        if node.settings.estimator.pose_refinement != 'off' or node.settings.estimator.odometry == 'none':
            # the refined pose, or the visual odometry's (the user has no other pose source then), in the odometry
            # frame ('odom' without odometry)
            self.pose = pub(PoseStamped, 'pose', out_qos)
        self.tf = None      # TF output (dpv_sensor.ros.tf_publisher), with publish_tf
        if s.publish_tf:
            try:
                from dpv_sensor.ros.tf_publisher import TfPublisher
                self.tf = TfPublisher(node, T_base_camera_44, base_frame=s.base_frame)
            except ImportError as exc:
                node.get_logger().error(f'publish_tf is set but tf2_msgs does not import ({exc}); no TF is published '
                                        '(make venv generates tf2_msgs; or source a ROS installation that has it)')
        # statistics
        self.rate = RateMeter(s.rate_window)          # depth/image (rgb, confidence: the same messages)
        self.points_rate = RateMeter(s.rate_window)
        self.n_points_skipped = 0                     # clouds skipped by points_max_rate
        self._last_points_stamp_ns = None
        self.latency_ms: collections.deque[float] = collections.deque(maxlen=200)   # receipt -> published
        self.age_ms: collections.deque[float] = collections.deque(maxlen=200)       # header stamp -> published
        self.n_published = self.n_keyframes_published = self.n_points = 0
        self.n_age_implausible = 0            # outputs whose stamp age says nothing (node_support.plausible_age_ms)
        # published outputs whose filter restarted (estimator, filter or pose-refinement restart; the first output of
        # the stream, whose filter starts by definition, is not counted) and the reason of the latest one
        self.n_output_resets = 0
        self.last_output_reset = ''
        self._keyframe_meta: collections.OrderedDict = collections.OrderedDict()
        self._frame_meta: collections.OrderedDict = collections.OrderedDict()

    def _publisher(self, msg_type, topic: str, qos_profile):
        self.matched[topic] = 0

        def on_matched(info, topic=topic) -> None:
            self.matched[topic] = int(info.current_count)
        return self.node.create_publisher(msg_type, qos.resolve(self.node, topic), qos_profile,
                                          event_callbacks=self._qos_events.publisher(topic, matched=on_matched))

    # ------------------------------------------------------------------------------------------ frame headers
    def remember(self, stamp_s: float, meta: FrameMeta, is_keyframe: bool, window_size: int) -> None:
        """Keep the headers (and, for keyframes, the images) of recent frames: a centered window of `window_size`
        publishes a keyframe's output two keyframes later and it must carry that frame's exact header."""
        store, cap = (self._keyframe_meta, 2 * window_size + 6) if is_keyframe else (self._frame_meta, 8)
        if not is_keyframe:
            meta = dataclasses.replace(meta, rgb=None)
        store[stamp_s] = meta
        while len(store) > cap:
            store.popitem(last=False)

    def forget(self) -> None:
        """The stream restarted: no output of the frames before will come."""
        self._keyframe_meta.clear()
        self._frame_meta.clear()

    def _lookup(self, stamp_s: float) -> FrameMeta | None:
        meta = self._keyframe_meta.get(stamp_s) or self._frame_meta.get(stamp_s)
        if meta is None:   # tolerate a float round trip inside the estimator
            for store in (self._keyframe_meta, self._frame_meta):
                for k, m in store.items():
                    if abs(k - stamp_s) < 1e-6:
                        return m
        return meta

    # ------------------------------------------------------------------------------------------ publishing
    def publish_output(self, out, rgb, stamp_ns: int, odom_frame: str) -> None:
        """Publish one DepthOutput (errors are reported, never raised). `rgb`, `stamp_ns`: the frame just pushed
        (its colours when the output is for it); `odom_frame`: the frame of the pose output."""
        try:
            self._publish(out, (stamp_ns / NS, rgb), odom_frame)
        except Exception as exc:
            self.faults.report(PUBLISH_ERROR, f'could not publish the output for {out.stamp:.3f} s: '
                               f'{type(exc).__name__}: {exc}', level='error')

    def _publish(self, out, current, odom_frame: str) -> None:
        """Publish one DepthOutput with the exact header of the input frame it belongs to."""
        meta = self._lookup(float(out.stamp))
        if meta is None:
            self.faults.report(UNKNOWN_OUTPUT, f'estimator output for {out.stamp:.6f} s matches no recent '
                               'input frame; not published', level='error')
            return
        rgb_src = meta.rgb
        if rgb_src is None and current is not None and current[0] == float(out.stamp):
            rgb_src = current[1]
        header = M.make_header(meta.stamp_ns, meta.frame_id)
        depth = np.asarray(out.depth_hw, dtype=np.float32)
        h, w = depth.shape
        K_out = self._output_K(out, meta, (w, h))
        rgb = None
        if rgb_src is not None:
            # the colour image at the output size (INTER_AREA, as the output K is the input K scaled to that size)
            rgb = rgb_src if rgb_src.shape[:2] == (h, w) else cv2.resize(rgb_src, (w, h), interpolation=cv2.INTER_AREA)
        self._publish_images(out, depth, rgb, K_out, header)
        if self.points.get_subscription_count() > 0 and rgb is not None:
            self._publish_points(depth, rgb, K_out, header, meta.stamp_ns)
        if self.pose is not None and out.T_world_cam_44 is not None:
            self.pose.publish(PM.matrix_to_pose_stamped(out.T_world_cam_44, M.make_header(meta.stamp_ns, odom_frame)))
            if self.tf is not None:
                self.tf.publish_refined(out.T_world_cam_44, meta.stamp_ns, odom_frame, meta.frame_id)
        self._count(out, meta)

    def _publish_images(self, out, depth, rgb, K_out, header) -> None:
        """depth, rgb and confidence images with their camera_info, and the compressed depth."""
        encoding = self.node.settings.node.depth_encoding
        conf = np.asarray(out.confidence_hw, dtype=np.float32)     # depth below min_confidence: NaN (estimator)
        h, w = depth.shape
        info = M.K_to_camera_info(K_out, w, h, header)     # every output's camera_info: K of this size, D zero
        self.depth.publish(M.depth_to_image(depth, header, encoding=encoding))
        self.depth_info.publish(info)
        if rgb is not None:
            self.rgb.publish(M.rgb_to_image(rgb, header))
            self.rgb_info.publish(info)
        else:
            self.faults.report(MISSING_RGB, f'no colour image kept for the output at {out.stamp:.3f} s; rgb/image '
                               'skipped', level='error')
        self.conf.publish(M.confidence_to_image(conf, header))
        self.conf_info.publish(info)
        if self.compressed is not None:
            self.compressed.publish(CD.depth_to_compressed_depth(depth, header, encoding=encoding))

    def _count(self, out, meta: FrameMeta) -> None:
        """The counters of a published output: output resets, rates, latency, stamp age."""
        reset_reason = getattr(out, 'reset_reason', None)
        if reset_reason and not (self.n_published == 0 and reset_reason == 'first frame'):
            self.n_output_resets += 1
            self.last_output_reset = f'{out.stamp:.3f} s: {reset_reason}'
            self.node.get_logger().info(f'output for {out.stamp:.3f} s follows a filter restart: {reset_reason}')
        now_ns = self.node.get_clock().now().nanoseconds     # the node's clock: ROS time with use_sim_time
        self.n_published += 1
        self.n_keyframes_published += int(bool(out.is_keyframe))
        self.rate.tick()
        self.latency_ms.append((time.monotonic() - meta.receipt_mono) * 1000.0)
        age = plausible_age_ms(now_ns, meta.stamp_ns)
        if age is None:
            self.n_age_implausible += 1
        else:
            self.age_ms.append(age)

    def _publish_points(self, depth, rgb, K, header, stamp_ns: int) -> None:
        """The organised cloud (every points_decimation-th pixel), at most points_max_rate per second of image
        time: an output closer than 1/rate to the previous cloud's stamp is skipped and counted."""
        s = self.node.settings.node
        max_rate = s.points_max_rate
        last = self._last_points_stamp_ns
        if max_rate > 0 and last is not None and 0 <= stamp_ns - last < NS / max_rate:
            self.n_points_skipped += 1
            return
        self._last_points_stamp_ns = stamp_ns
        self.points.publish(C.depth_to_pointcloud_decimated(depth, rgb, K, header, decimation=s.points_decimation))
        self.n_points += 1
        self.points_rate.tick()

    def _output_K(self, out, meta: FrameMeta, out_wh) -> np.ndarray:
        """K of the output image: the input K scaled (in float64) from the input size to the output size. The
        estimator's own K_33 (computed in float32 on its device) must agree; if it does not, it is used as is."""
        K_est = np.asarray(out.K_33, dtype=np.float64)
        in_wh = (meta.in_w, meta.in_h)
        K = np.array(meta.K_in, dtype=np.float64) if in_wh == tuple(out_wh) else M.scale_K(meta.K_in, in_wh, out_wh)
        if not np.allclose(K, K_est, rtol=1e-4, atol=1e-3):
            self.faults.report(OUTPUT_K_MISMATCH, f'estimator output K {K_est.round(3).tolist()} differs from the '
                               f'input K scaled to {out_wh[0]}x{out_wh[1]} ({K.round(3).tolist()}); publishing the '
                               "estimator's", level='warn', count=False)
            return K_est
        return K
