"""The node's inputs: the subscriptions of image, camera_info and odometry with their QoS (input_reliability auto
follows what the publishers offer), the callbacks that store what arrives (callbacks only store: the newest image
waits in the one-slot mailbox, odometry goes into the pose buffer, camera_info sets K and the rectifier), and the
worker's wait for the camera_info and the odometry pose of an image (``wait_for``).

With ``image_transport: compressed`` the image subscription is sensor_msgs/CompressedImage on ``image/compressed``
(following a remapped ``image`` as image_transport names it); each message takes the raw image's path and is
decoded on receipt (``dpv_sensor.ros.compressed_image``) once the receipt takes its size (read from its header).

Images are checked on receipt (``dpv_sensor.ros.receipt``), so a bad one is counted and logged even when the
newest-wins mailbox would have replaced it; images lost before the callback are counted by ``stream_loss``; a change
of the odometry frame_id is logged and counted (faults.odometry_frame_change). The camera mount the odometry is
composed with comes from ``extrinsic`` (the T_base_camera parameter, or /tf_static and /tf). An image stamped ahead
of the node's clock and the newest odometry by more than future_stamp_tolerance is not waited for
(``continuity.future_stamp``).
"""
from __future__ import annotations

import collections
import threading
import time

import numpy as np
from nav_msgs.msg import Odometry
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

from dpv_sensor.core.rectify import RectifierCache, UnsupportedDistortion
from dpv_sensor.ros import msgs as M
from dpv_sensor.ros import pose_msgs as PM
from dpv_sensor.ros import qos
from dpv_sensor.ros.compressed_image import decode_message
from dpv_sensor.ros.extrinsic import CameraExtrinsic
from dpv_sensor.ros.odometry_covariance import OdometryCovariances
from dpv_sensor.ros.fault_kinds import (BAD_CAMERA_INFO, BUSY, EMPTY_FRAME_ID, NAN_ODOMETRY, NO_EXTRINSIC,
                                        ODOM_CONFLICT, ODOM_JUMP, ODOM_LATE, ODOM_ZERO_STAMP,
                                        TIME_BACKWARDS, UNSUPPORTED_DISTORTION)
from dpv_sensor.ros.node_support import Incoming, Mailbox, OdometryWait, RateMeter, merge_incoming
from dpv_sensor.ros.receipt import ImageReceipt, OdomFrameWatch
from dpv_sensor.ros.stream_loss import StreamLoss
from dpv_sensor.ros.transport import choose_reliability
from dpv_sensor.stream.continuity import future_stamp
from dpv_sensor.stream.pose_buffer import FUTURE, PoseBuffer, PoseQuery

NO_MOUNT = 'no mount'    # PoseQuery.reason: no camera mount (TF) for the image yet
FROM_THE_FUTURE = 'from the future'   # PoseQuery.reason: stamped ahead of the clock and the odometry (future_stamp)


def replaced_drop_kind(reason: str | None) -> str:
    """What an image replaced in the mailbox while the worker waited for the pose of the image before it is counted
    as, by how that wait ended (the PoseQuery.reason it ended with; None: it got the pose, or waited for camera_info):
    the odometry never came within odom_wait_timeout ('future': dropped.odometry_late), the camera mount was not on TF
    (NO_MOUNT: dropped.no_extrinsic, as the image waited for); anything else (the pose came, or the odometry came
    and failed: a gap, too old, invalid) is the usual busy worker (dropped.busy): the odometry was not late."""
    if reason == FUTURE:
        return ODOM_LATE
    if reason == NO_MOUNT:
        return NO_EXTRINSIC
    return BUSY

NS = 1_000_000_000
# input_reliability auto: seconds between looks at what each input's publishers offer. Until the first look after a
# publisher appears the input keeps its first QoS, and what is sent across the re-subscription is lost. At 1 s the
# node followed a reliable camera 0.72 s after it was ready, at 0.2 s within 0.2 s; a look is one graph query per
# input, about 55 microseconds.
QOS_CHECK_PERIOD_S = 0.2


class NodeInputs:
    """Subscriptions, their QoS and what the callbacks store. `node`: the rclpy node (its ``settings`` are read
    at use); `drop(reason)`: counts an image the node refuses (dropped.*)."""

    def __init__(self, node, faults, qos_events: qos.QosEvents, drop, T_base_camera_44, extrinsic_source: str):
        s = node.settings.node
        self.node = node
        self.faults = faults
        self._qos_events = qos_events
        est = node.settings.estimator
        self.pose_buffer = PoseBuffer(max_gap_s=s.max_odom_gap, history_s=max(10.0, 4 * s.max_odom_gap),
                                      max_speed=est.odom_max_speed, max_rate_deg=est.odom_max_rate_deg)
        # the odometry's pose and twist covariance, checked (invalid ones counted and kept as not filled)
        self.covariances = OdometryCovariances(faults, lambda: node.settings.estimator.pose_uncertainty)
        self.cv = threading.Condition()               # notified when odometry or camera_info arrives
        self._K = None                                # (K 3x3, (w, h)) from camera_info or the parameters
        if s.camera_info_source == 'parameters':
            self._K = (np.array([[s.fx, 0.0, s.cx], [0.0, s.fy, s.cy], [0.0, 0.0, 1.0]]), (0, 0))
        self._rectifiers = RectifierCache()           # distorted camera_info: undistortion maps of the latest one
        self._rectifier = None                        # the Rectifier of the current camera_info (None: as-is)
        self.odom_frame = 'odom'
        self._odom_seen = False                       # any odometry received yet (a first stamp 0 is a clock at 0)
        self.odom_child_frame = ''                    # child_frame_id of the latest odometry: the mount's parent
        # the camera mount (T_base_camera): the parameter, or looked up on /tf_static and /tf per image
        self.extrinsic = CameraExtrinsic(node, faults, extrinsic_source, s.extrinsic_source, T_base_camera_44,
                                         on_update=self.wake)
        self.tf = None                                # the TF output (set by the node), told the frame names
        # images lost before on_image are counted by stream_loss (callback thread only)
        self.stream_loss = StreamLoss()
        self._receipt = ImageReceipt(faults, drop, self.stream_loss, size_change_images=s.size_change_images)
        self._odom_frames = OdomFrameWatch(faults)
        self.mailbox = Mailbox(merge=merge_incoming)
        self._drop = drop
        self.odometry_wait = OdometryWait()   # the worker waits for odometry after an image's stamp (wait_for)
        self.in_rate = RateMeter()
        self.n_received = 0
        self.n_odometry_received = 0                  # odometry messages taken by on_odom, whatever became of them
        self.first_image_mono = None
        self.last_image_mono = None
        self.image_transport = s.image_transport
        self.decode_ms: collections.deque[float] = collections.deque(maxlen=200)   # compressed: decode per image
        self._callbacks = {'image': (CompressedImage, self.on_compressed_image) if s.image_transport == 'compressed'
                           else (Image, self.on_image)}
        # the name each input subscribes (qos.resolve: a transport follows its remapped image topic)
        self._names = {'image': 'image/compressed'} if s.image_transport == 'compressed' else {}
        if s.camera_info_source == 'topic':
            self._callbacks['camera_info'] = (CameraInfo, self.on_camera_info)
        if est.odometry == 'topic':
            self._callbacks['odom'] = (Odometry, self.on_odom)
        self.subscriptions: dict = {}
        self.reliability: dict = {}
        self.matched: dict = {}                       # DDS-matched publishers per input (subscription events)
        for topic in self._callbacks:
            self.subscribe(topic, 'reliable' if s.input_reliability == 'reliable' else 'best_effort')

    # ------------------------------------------------------------------------------------------ QoS
    def topic_name(self, topic: str) -> str | None:
        """The resolved name of an input's subscription, None when there is none."""
        sub = self.subscriptions.get(topic)
        return None if sub is None else sub.topic_name

    def subscribe(self, topic: str, reliability: str) -> None:
        """(Re)create the subscription of input `topic` with `reliability`; the image subscription also counts the
        samples the middleware reports lost (where it reports them: Fast DDS does for best-effort readers)."""
        old = self.subscriptions.pop(topic, None)
        if old is not None:
            self.node.destroy_subscription(old)
        # DDS "subscription matched": a publisher the graph lists is not necessarily matched by this reader yet,
        # and what it sends before the match is lost (volatile); a new subscription starts unmatched
        self.matched[topic] = 0

        def on_matched(info, topic=topic) -> None:
            self.matched[topic] = int(info.current_count)
        lost = None
        if topic == 'image':
            lost = lambda info: self.stream_loss.on_rmw_lost(int(info.total_count_change))  # noqa: E731
        events = self._qos_events.subscription(topic, matched=on_matched, message_lost=lost)
        msg_type, callback = self._callbacks[topic]
        self.subscriptions[topic] = self.node.create_subscription(
            msg_type, qos.resolve(self.node, self._names.get(topic, topic)), callback,
            qos.profile(reliability, self.node.settings.node.input_depth), event_callbacks=events)
        self.reliability[topic] = reliability

    def adapt_qos(self) -> None:
        """input_reliability auto: follow what the publishers of each input offer (transport.choose_reliability):
        reliable while every publisher is reliable (lost samples are repaired), else best effort."""
        for topic, sub in list(self.subscriptions.items()):
            try:
                infos = self.node.get_publishers_info_by_topic(sub.topic_name)
            except Exception:   # the graph is not available (shutting down): try again next time
                continue
            offered = [qos.offered_reliability(i) for i in infos]
            want = choose_reliability('auto', offered)
            if want != self.reliability[topic]:
                self.node.get_logger().info(f"input {sub.topic_name}: publishers offer "
                                            f"{', '.join(sorted(set(offered)))}; subscribing {want}")
                self.subscribe(topic, want)

    # ------------------------------------------------------------------------------------------ callbacks
    def on_image(self, msg, info, decode=None) -> None:
        """An image and its message info (rclpy passes it to a callback of two arguments: a dict with the
        publication sequence number, where the middleware gives one); `decode`: for a compressed image, its decoder
        (the receipt calls it once the image's size is taken)."""
        self.n_received += 1
        self.last_image_mono = time.monotonic()
        if self.first_image_mono is None:
            self.first_image_mono = self.last_image_mono
        self.in_rate.tick(self.last_image_mono)
        try:
            stamp_ns = M.stamp_to_ns(msg.header.stamp)
        except Exception:   # a malformed header is reported by the worker; no gap to measure here
            stamp_ns = None
        if not msg.header.frame_id:
            self._on_empty_frame_id(stamp_ns)
        seq = info.get('publication_sequence_number') if isinstance(info, dict) else None
        # a second camera, lost images, stamp jumps and unusable images: judged here, before the mailbox
        # (dpv_sensor.ros.receipt)
        item = self._receipt.image(msg, stamp_ns, time.monotonic(), time.time_ns(), seq=seq, source='image',
                                   decode=decode)
        if item is None:
            return
        if self.tf is not None:
            self.tf.frames(image_frame=msg.header.frame_id or self.node.settings.node.frame_id)
        if self.mailbox.put(item) and self.odometry_wait.replaced():
            self._count_replaced(1, BUSY)

    def _count_replaced(self, n: int, kind: str) -> None:
        """`n` images replaced in the mailbox by newer ones, counted as `kind`: why the worker could not take them
        (``replaced_drop_kind``): it waited for odometry that did not come in time (dropped.odometry_late), for the
        camera mount on TF (dropped.no_extrinsic, logged with the image it waited for), or it was busy
        (dropped.busy)."""
        if n <= 0:
            return
        for _ in range(n):
            self._drop(kind)
        if kind == ODOM_LATE:
            self.faults.report(ODOM_LATE, f'odometry arrives later than the images: {n} image(s) dropped while the '
                               'worker waited for the odometry of the one before, which did not come within '
                               f'odom_wait_timeout {self.node.settings.node.odom_wait_timeout:g} s '
                               '(dropped.odometry_late counts them)', count=False, period_s=30.0)
        elif kind == BUSY:
            self.faults.report(BUSY, 'estimator busy: dropping an older image that was still waiting (newest wins; '
                               'the count is in /diagnostics)', level='info', count=False, period_s=60.0)

    def on_compressed_image(self, msg, info) -> None:
        """image_transport compressed: the raw image's path with the same message info (two arguments, so rclpy
        passes it) and the decoder (JPEG / PNG), which the receipt calls once it takes the image's size (read from
        the header); a payload that cannot be decoded is counted (stream loss, received) and refused there."""
        self.on_image(msg, info, decode=self._decode)

    def _decode(self, msg):
        """A CompressedImage -> compressed_image.DecodedImage, timed (image_decode_ms_median)."""
        t0 = time.perf_counter()
        decoded = decode_message(msg)
        self.decode_ms.append((time.perf_counter() - t0) * 1000.0)
        return decoded

    def _on_empty_frame_id(self, stamp_ns) -> None:
        """An image without header.frame_id: the outputs use the frame_id parameter (warned once, every one counted)."""
        if self.faults.counts[EMPTY_FRAME_ID] == 0:
            at = f' (first at {stamp_ns / NS:.3f} s)' if stamp_ns is not None else ''
            self.faults.report(EMPTY_FRAME_ID, f"images arrive with an empty header.frame_id{at}; the outputs use the "
                               f"frame_id parameter '{self.node.settings.node.frame_id}' (the camera driver should "
                               'set its optical frame; this is not logged again, faults.empty_frame_id counts them)')
        else:
            self.faults.count(EMPTY_FRAME_ID)

    def on_camera_info(self, msg) -> None:
        where = self.topic_name('camera_info')
        try:
            K, size = M.camera_info_to_K(msg)
        except M.BadCameraInfo as exc:
            self.faults.report(BAD_CAMERA_INFO, f'ignoring camera_info on {where}: {exc}')
            return
        rect = None
        if M.has_distortion(msg):
            try:
                rect = self._rectifiers.for_camera_info(msg)
            except UnsupportedDistortion as exc:
                self.faults.report(UNSUPPORTED_DISTORTION, f'cannot rectify the images of camera_info on {where}: '
                                   f'{exc}; images are used as they are (depth is less accurate towards the borders)',
                                   period_s=60.0)
            if rect is not None:
                K = np.array(rect.K, dtype=np.float64)
        with self.cv:
            self._K = (K, size)
            self._rectifier = rect
            self.cv.notify_all()

    def on_odom(self, msg) -> None:
        self.n_odometry_received += 1
        stamp_ns = M.stamp_to_ns(msg.header.stamp)
        # a clock that starts at 0 (a simulator, a bag written from stamps 0 on) stamps its first message 0; a zero
        # stamp after any other odometry is a driver that does not stamp its messages
        first, self._odom_seen = not self._odom_seen, True
        if stamp_ns == 0 and not first:
            self.faults.report(ODOM_ZERO_STAMP, 'odometry header.stamp is zero: the driver does not stamp its '
                               'messages; ignoring them (images are paired with odometry by stamp; '
                               'faults.odometry_zero_stamp counts them)', period_s=30.0)
            return
        try:
            T = PM.odometry_to_matrix(msg)
        except M.BadOdometry as exc:
            self.faults.report(NAN_ODOMETRY, f'ignoring odometry at {stamp_ns / NS:.3f} s: {exc}; images '
                               'interpolated across it are dropped')
            T = None
        self.odom_frame = self._odom_frames.update(msg.header.frame_id, stamp_ns)
        self.odom_child_frame = msg.child_frame_id
        if self.tf is not None and msg.child_frame_id:
            self.tf.frames(odom_child_frame=msg.child_frame_id)
        buffer = self.pose_buffer
        jumps, conflicts = buffer.jumps, buffer.conflicts
        cleared = buffer.add(stamp_ns, T)
        self.covariances.add(msg, stamp_ns)
        if buffer.conflicts != conflicts:
            self.faults.report(ODOM_CONFLICT, f'{buffer.last_conflict}; keeping the first (two odometry '
                               'sources publishing on one topic?)')
        if cleared and buffer.jumps != jumps:
            self.faults.report(ODOM_JUMP, f'{cleared}: images before it are dropped and the estimator restarts '
                               '(relocalisation or loop closure in the odometry frame?)')
        elif cleared:
            self.faults.report(TIME_BACKWARDS, f'time went backwards: {cleared} (bag restarted or simulator reset?)',
                               key='time_backwards:odometry')
        with self.cv:
            self.cv.notify_all()

    # ------------------------------------------------------------------------------------------ the worker's side
    @property
    def rectifier(self):
        """The Rectifier of the current camera_info, None when the images are used as they are."""
        with self.cv:
            return self._rectifier

    def wait_for(self, item: Incoming, stamp_ns: int, stop: threading.Event):
        """Wait (at most odom_wait_timeout after the image arrived) for camera_info, a pose at `stamp_ns` and the
        camera mount.

        Returns (K, camera_info size, T_world_cam | None, None) when all are there, else (None, None, None, why):
        why is None when no camera_info has arrived, else the PoseQuery whose reason ('future' once the timeout
        passed, 'gap', 'too old', 'nan', NO_MOUNT: no camera mount from TF, or FROM_THE_FUTURE: the image is stamped
        ahead of the node's clock and the newest odometry by more than future_stamp_tolerance, not waited for) and
        detail say why there is no pose. Images replaced in the mailbox meanwhile are counted by how the wait ended
        (``replaced_drop_kind``).
        """
        result = None
        try:
            result = self._wait_for(item, stamp_ns, stop)
            return result
        finally:
            why = None if result is None else result[3]
            self._count_replaced(self.odometry_wait.end(), replaced_drop_kind(None if why is None else why.reason))

    def _wait_for(self, item: Incoming, stamp_ns: int, stop: threading.Event):
        deadline = item.receipt_mono + self.node.settings.node.odom_wait_timeout
        # the odometry's time of the image (odom_time_offset_ms: the odometry's stamps against the images')
        stamp_ns = stamp_ns + int(round(self.node.settings.node.odom_time_offset_ms * 1e6))
        need_pose = self.node.settings.estimator.odometry == 'topic'
        while True:
            with self.cv:
                K = self._K
            query = self._camera_pose(item, stamp_ns) if need_pose else None
            if K is not None and (not need_pose or query.ok):
                return K[0], K[1], (query.T_world_cam_44 if need_pose else None), None
            if need_pose and query.reason == FUTURE:     # no odometry after the stamp yet: will it come?
                ahead = future_stamp(stamp_ns, self.node.get_clock().now().nanoseconds, self.pose_buffer.newest_ns,
                                     self.node.settings.node.future_stamp_tolerance)
                if ahead is not None:
                    return None, None, None, PoseQuery(None, FROM_THE_FUTURE, ahead)
            if K is not None and need_pose and query.reason not in (FUTURE, NO_MOUNT):
                return None, None, None, query          # waiting cannot help (gap, too old, invalid odometry)
            if time.monotonic() >= deadline or stop.is_set():
                return None, None, None, (query if K is not None else None)
            if K is not None and need_pose:     # the odometry after the stamp keeps the worker (OdometryWait)
                self.odometry_wait.start()
            with self.cv:
                self.cv.wait(min(max(deadline - time.monotonic(), 0.0), 0.05))

    def image_frames(self, item: Incoming) -> tuple[str, str]:
        """(the mount's parent: the odometry's child_frame_id or else base_frame, the image's frame)."""
        s = self.node.settings.node
        return self.odom_child_frame or s.base_frame, item.msg.header.frame_id or s.frame_id

    def _camera_pose(self, item: Incoming, stamp_ns: int) -> PoseQuery:
        """The odometry pose at the stamp composed with the camera mount of the image's frame."""
        query = self.pose_buffer.base_pose_at(stamp_ns)
        if not query.ok:
            return query
        base, image = self.image_frames(item)
        T_base_camera, why = self.extrinsic.lookup(base, image)
        if T_base_camera is None:
            return PoseQuery(None, NO_MOUNT, why)
        return self.pose_buffer.pose_at(stamp_ns, T_base_camera)

    def wake(self) -> None:
        """Wake a worker waiting in :meth:`wait_for` (the node stops)."""
        with self.cv:
            self.cv.notify_all()

