"""`ros2 run dpv_sensor node`: the rclpy adapter of the virtual depth camera.

This module owns ROS plumbing only: parameters, QoS, subscriptions, publishing, diagnostics, signals. The
algorithm lives in dpv_sensor.stream.estimator (Estimator.push(Frame) -> DepthOutput | None); messages are converted by
dpv_sensor.ros.msgs; image poses come from dpv_sensor.stream.pose_buffer.

Topics (relative names, remappable; a camera_info or compressedDepth follows its remapped image topic as
image_transport names them, unless remapped itself: dpv_sensor.ros.topic_names):
  in   image (sensor_msgs/Image rgb8/bgr8/rgba8/bgra8/mono8), camera_info (sensor_msgs/CameraInfo),
       odom (nav_msgs/Odometry) - QoS: input_reliability (auto: as the publishers offer), input_depth; transport:
       dpv_sensor.ros.transport (docs/transport.md), applied by the entry point before rclpy starts
  out  depth/image (32FC1 m, NaN = none | 16UC1 mm, 0 = none), depth/camera_info (K of the output size),
       rgb/image (rgb8: the colour image the depth was computed for, rectified when the node rectifies, at the
       depth's size) + rgb/camera_info, confidence/image (32FC1 in [0, 1]) + confidence/camera_info (all camera_info
       the same: K of the output size, D zero), depth/image/compressedDepth (with publish_compressed_depth),
       depth/points (PointCloud2 XYZRGB, only computed while subscribed; points_decimation, points_max_rate),
       pose (PoseStamped, with pose_refinement or odometry none), /diagnostics (DiagnosticArray)
       with publish_tf: /tf_static (base_frame -> image frame, T_base_camera) and /tf (<image frame>_refined,
       with the pose output), tf2_msgs/TFMessage (dpv_sensor.ros.tf_publisher)

Threading: callbacks only store messages. The newest image waits in a one-slot mailbox ("newest wins": an image
that is still waiting when a newer one arrives is dropped and counted) and a worker thread converts it, waits up to
odom_wait_timeout for odometry after its stamp, runs the estimator and publishes. Memory stays flat whatever the
input rate. Dropping is deliberate and does not break the stream: every Frame carries `sensor_gap_s`, the longest
interval between consecutive images the node *received* since the previous frame it pushed (dropped images
included), so the estimator's time-gap reset fires only when the camera stream itself stalled; its jump rules judge
the motion against the elapsed time, so a slow machine that pushes a frame every few seconds keeps its filter.
Every output carries exactly the input image's header (stamp and frame_id). The worker builds the estimator when
the node starts ('starting' is logged once topics and parameters are up, 'ready' once the model is loaded); if it
cannot be built (e.g. measurement=network without weights) the node logs that one error and exits with code 2.
SIGINT / SIGTERM stop the node cleanly (exit 0), also while it is still starting: the entry point
(dpv_sensor.ros.entry) installs the handlers before this module's heavy imports.

Distorted input (camera_info with non-zero D, plumb_bob / rational_polynomial / equidistant) is rectified
(dpv_sensor.core.rectify) before the estimator; every output then carries the rectified K with D zero.

Diagnostics: per output a measured rate against expected_depth_rate / expected_points_rate, the share of recent
images lost in transport (lost.transport) or rejected as faulty (dropped.* other than busy) against drop_warn_share /
drop_error_share, the stamp age on the node's clock (sim time works), incompatible QoS events per topic.

Bad input never stops the node: each kind of fault (unsupported encoding, inconsistent image, size change,
missing or zero camera_info, NaN odometry, odometry gap or timeout, conflicting odometry at one stamp, time going
backwards, an empty image frame_id, a degenerate image, an exception inside the estimator) is counted, reported in
/diagnostics and logged with a specific, rate-limited message. No image is lost uncounted: images lost before the
callback (transport) are counted from the stamps and the middleware's reports (lost.*), images the node skips or
refuses in dropped.*, so frames_received + lost.transport = images sent and frames_processed + dropped_total =
frames_received (but for the one or two in flight). A loss is counted only on evidence (a middleware report, or a
stamp gap the stream around it confirms): a camera that lowers its rate loses nothing (input_rate_changes) and a
stamp jump is a discontinuity (input_stamp_jumps, faults.stamp_jump). Images are checked on receipt
(dpv_sensor.ros.receipt), so a bad one is counted and logged even when the newest-wins mailbox would have replaced it;
a change of the odometry frame_id is logged and counted (faults.odometry_frame_change).
"""
from __future__ import annotations

if __name__ == '__main__':     # python -m dpv_sensor.ros.node: signal handlers before the heavy imports below
    from dpv_sensor.ros.entry import prepare as _prepare
    _prepare()

import collections
import sys
import threading
import time
import traceback
from dataclasses import dataclass

import cv2
import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry
from rclpy.clock import Clock, ClockType
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2

from dpv_sensor.stream import continuity
from dpv_sensor.ros import msgs as M
from dpv_sensor import params as P
from dpv_sensor.stream.estimator import EstimatorConfig
from dpv_sensor.stream.frame import Frame
from dpv_sensor.ros.node_params import RuntimeParameters, declare_parameters
from dpv_sensor.ros.node_support import (FaultLog, Incoming, LogBridge, Mailbox, RateMeter, camera_gap_ns, max_gap,
                                     merge_incoming, plausible_age_ms)
from dpv_sensor.stream.pipeline import DEGENERATE, VO_LOST, Pipeline
from dpv_sensor.stream.pose_buffer import CovarianceTrack, PoseBuffer, pose7_to_matrix
from dpv_sensor.core.rectify import RectifierCache, UnsupportedDistortion
from dpv_sensor.ros.receipt import BAD_IMAGE, UNSUPPORTED_ENCODING, ImageReceipt, OdomFrameWatch
from dpv_sensor.ros.stream_loss import StreamLoss
from dpv_sensor.ros.topic_names import topic_name
from dpv_sensor.ros.transport import choose_reliability

NODE_NAME = 'dpv_sensor'
NS = 1_000_000_000

# fault kinds (counter names in /diagnostics; each has its own log message)
SIZE_CHANGE = 'image_size_change'
NO_CAMERA_INFO = 'no_camera_info'
BAD_CAMERA_INFO = 'bad_camera_info'
CAMERA_INFO_MISMATCH = 'camera_info_size_mismatch'
NAN_ODOMETRY = 'nan_odometry'
ODOM_JUMP = 'odometry_jump'
ODOM_GAP = 'odometry_gap'
ODOM_TIMEOUT = 'odometry_timeout'
ODOM_TOO_OLD = 'odometry_too_old'
ODOM_INVALID = 'odometry_invalid_bracket'
ODOM_CONFLICT = 'odometry_conflict'            # two messages at one stamp with different poses (the first is kept)
EMPTY_FRAME_ID = 'empty_frame_id'              # an image without header.frame_id (the frame_id parameter is used)
TIME_BACKWARDS = 'time_backwards'
DUPLICATE_STAMP = 'duplicate_stamp'
ESTIMATOR_EXCEPTION = 'estimator_exception'
PUBLISH_ERROR = 'publish_error'
UNKNOWN_OUTPUT = 'unknown_output_stamp'
INTERNAL_ERROR = 'internal_error'
BUSY = 'busy'
UNSUPPORTED_DISTORTION = 'unsupported_distortion'
RECTIFY_SIZE = 'rectify_size_mismatch'
MISSING_RGB = 'missing_output_colour'
INCOMPATIBLE_QOS = 'incompatible_qos'

# How long after its receipt an image waits for the middleware's report of images lost right before it (Fast DDS
# reports them when the next sample arrives, but the report and the image reach the node by separate callbacks):
# a gap the report explains is no gap in the camera stream. Only images that end a gap no report explains yet wait.
LOSS_REPORT_WAIT_S = 0.2


def self_check() -> int:
    """Import every heavy dependency the node needs and print versions; 0 when all import."""
    failures = []
    versions = {}
    for mod in ('rclpy', 'torch', 'cv2', 'gtsam', 'numpy', 'rosbags', 'safetensors',
                'sensor_msgs.msg', 'nav_msgs.msg', 'diagnostic_msgs.msg', 'tf2_msgs.msg'):
        try:
            m = __import__(mod, fromlist=['_'])
            versions[mod] = getattr(m, '__version__', 'ok')
        except Exception as exc:  # report every missing piece, not only the first
            failures.append(f'{mod}: {exc}')
    for mod, ver in versions.items():
        print(f'  {mod:22s} {ver}')
    try:
        P.validate(P.defaults())
    except P.ParameterError as exc:
        failures.append(f'default parameters: {exc}')
    if failures:
        print('self-check FAILED:\n  ' + '\n  '.join(failures), file=sys.stderr)
        return 1
    print('self-check ok')
    return 0


class StartupError(RuntimeError):
    """The node cannot start (e.g. the estimator cannot be built with the given parameters)."""


@dataclass
class _FrameMeta:
    stamp_ns: int        # the image's header stamp, exactly
    frame_id: str
    rgb: object          # HxWx3 uint8 (kept for keyframes: the point cloud colours, visual odometry)
    K_in: object         # intrinsics of the input image (float64)
    in_w: int
    in_h: int
    receipt_mono: float
    receipt_ns: int


# --------------------------------------------------------------------------------------------------------------
# the node
# --------------------------------------------------------------------------------------------------------------
class DepthCameraNode(Node):
    """The virtual depth camera on the ROS graph (parameters, topics, diagnostics)."""

    def __init__(self, **kwargs):
        super().__init__(NODE_NAME, **kwargs)

        self.config = cfg = declare_parameters(self)
        log = self.get_logger()
        self.faults = FaultLog(log)
        self.dropped: collections.Counter = collections.Counter()
        self._stats_lock = threading.Lock()
        self._log_bridge = LogBridge(log).attach()

        # --- the estimator is built by the worker thread (loading weights / CUDA can take seconds; the node
        # meanwhile buffers odometry, keeps the newest image and reports 'starting' in /diagnostics) ----------
        self.pipeline: Pipeline | None = None
        self.fatal_error: str | None = None
        self.failed = threading.Event()           # set by the worker when the pipeline cannot be built
        self._estimator_lock = threading.RLock()

        # --- pose buffer and camera intrinsics -------------------------------------------------------------
        self.T_base_camera = pose7_to_matrix(cfg['T_base_camera'])
        self.pose_buffer = PoseBuffer(max_gap_s=cfg['max_odom_gap'], history_s=max(10.0, 4 * cfg['max_odom_gap']),
                                      T_base_camera_44=self.T_base_camera, max_speed=cfg['odom_max_speed'],
                                      max_rate_deg=cfg['odom_max_rate_deg'])
        self.pose_covariance = CovarianceTrack()     # the odometry's pose covariance (pose_uncertainty: auto)
        self._inputs_cv = threading.Condition()      # notified when odometry or camera_info arrives
        self._K = None                                # (K 3x3, (w, h)) from camera_info or the parameters
        if cfg['camera_info_source'] == 'parameters':
            self._K = (np.array([[cfg['fx'], 0.0, cfg['cx']], [0.0, cfg['fy'], cfg['cy']], [0.0, 0.0, 1.0]]),
                       (0, 0))
        self._rectifiers = RectifierCache()           # distorted camera_info: undistortion maps of the latest one
        self._rectifier = None                        # the Rectifier of the current camera_info (None: as-is)
        self.qos_incompatible: collections.Counter = collections.Counter()   # incompatible QoS events per topic
        self._odom_frame = 'odom'

        # --- QoS, subscriptions, publishers ------------------------------------------------------------------
        rel = {'best_effort': ReliabilityPolicy.BEST_EFFORT, 'reliable': ReliabilityPolicy.RELIABLE}
        out_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=cfg['output_depth'],
                             reliability=rel[cfg['output_reliability']], durability=DurabilityPolicy.VOLATILE)
        # inputs at the reliability the publishers offer (input_reliability auto: see _adapt_input_qos); images lost
        # before _on_image are counted by stream_loss (callback thread only)
        self.stream_loss = StreamLoss()
        self._receipt = ImageReceipt(self.faults, self._drop, self.stream_loss)
        self._odom_frames = OdomFrameWatch(self.faults)
        self._inputs = {'image': (Image, self._on_image)}
        if cfg['camera_info_source'] == 'topic':
            self._inputs['camera_info'] = (CameraInfo, self._on_camera_info)
        if cfg['odometry'] == 'topic':
            self._inputs['odom'] = (Odometry, self._on_odom)
        self._input_subs: dict = {}
        self._input_reliability: dict = {}
        self._input_matched: dict = {}                # DDS-matched publishers per input (subscription events)
        for topic in self._inputs:
            self._subscribe_input(topic, 'reliable' if cfg['input_reliability'] == 'reliable' else 'best_effort')
        if cfg['input_reliability'] == 'auto':
            self.create_timer(1.0, self._adapt_input_qos)
        pub = self._publisher
        self.pub_depth = pub(Image, 'depth/image', out_qos)
        self.pub_depth_info = pub(CameraInfo, 'depth/camera_info', out_qos)
        # the colour image each depth was computed for, with the same header, size and K (rtabmap's rgbd_sync and
        # depth_image_proc pair them by exact stamp; the camera's own colour stream has no image at most stamps
        # of the keyframe outputs)
        self.pub_rgb = pub(Image, 'rgb/image', out_qos)
        self.pub_rgb_info = pub(CameraInfo, 'rgb/camera_info', out_qos)
        self.pub_conf = pub(Image, 'confidence/image', out_qos)
        self.pub_conf_info = pub(CameraInfo, 'confidence/camera_info', out_qos)
        self.pub_compressed = None
        if cfg['publish_compressed_depth']:
            # image_transport's topic name for the compressedDepth transport of depth/image
            self.pub_compressed = pub(CompressedImage, 'depth/image/compressedDepth', out_qos)
        self.pub_points = pub(PointCloud2, 'depth/points', out_qos)
        self.pub_pose = None
        if cfg['pose_refinement'] != 'off' or cfg['odometry'] == 'none':
            # the refined pose, or the visual odometry's (the user has no other pose source then), in the odometry
            # frame ('odom' without odometry)
            self.pub_pose = pub(PoseStamped, 'pose', out_qos)
        self.pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self.tf = None      # TF output (dpv_sensor.ros.tf_publisher), with publish_tf
        if cfg['publish_tf']:
            try:
                from dpv_sensor.ros.tf_publisher import TfPublisher
                self.tf = TfPublisher(self, self.T_base_camera, base_frame=cfg['base_frame'])
            except ImportError as exc:
                log.error(f'publish_tf is set but tf2_msgs does not import ({exc}); no TF is published '
                          '(make venv generates tf2_msgs; or source a ROS installation that has it)')

        # --- statistics ----------------------------------------------------------------------------------------
        self.in_rate = RateMeter()
        self.out_rate = RateMeter(cfg['rate_window'])      # depth/image (rgb, confidence: the same messages)
        self.points_rate = RateMeter(cfg['rate_window'])
        self.n_points_skipped = 0                          # clouds skipped by points_max_rate
        self._last_points_stamp_ns = None
        self._first_image_mono = None
        # (mono, received, faulty, lost) at each diagnostics tick, from the start (nothing received yet)
        self._share_history: collections.deque = collections.deque([(time.monotonic(), 0, 0.0, 0.0)])
        self.latency_ms: collections.deque[float] = collections.deque(maxlen=200)   # receipt -> published
        self.age_ms: collections.deque[float] = collections.deque(maxlen=200)       # header stamp -> published
        self.process_ms: collections.deque[float] = collections.deque(maxlen=200)   # estimator.push, any frame
        self.keyframe_ms: collections.deque[float] = collections.deque(maxlen=50)   # estimator.push, keyframes
        self.n_received = self.n_processed = self.n_published = self.n_keyframes_published = 0
        self.n_points = 0
        self.n_age_implausible = 0            # outputs whose stamp is more than an hour off the node's clock
        self._node_resets = 0
        # published outputs whose filter restarted (estimator, filter or pose-refinement restart; the first output of
        # the stream, whose filter starts by definition, is not counted) and the reason of the latest one
        self.n_output_resets = 0
        self._last_output_reset = ''
        self._last_keyframe_ms = None
        self._last_fault_total = 0
        self._last_exception_count = 0
        self._started_mono = time.monotonic()
        self._last_image_mono = None
        self._last_push_ms = 0.0
        self._degenerate_run = 0              # consecutive degenerate images (worker thread only)
        self._degenerate_reason = ''
        self.n_degenerate_episodes = 0

        # --- worker ---------------------------------------------------------------------------------------------
        self._mailbox = Mailbox(merge=merge_incoming)
        self._last_received_stamp_ns = None   # header stamp of the newest image received (callback thread only)
        self._gap_carry_ns = None             # longest image gap since the last push (worker thread only)
        self._loss_carry: list = []           # stream_loss.Gap of images lost since the last push (worker thread)
        self._stop = threading.Event()
        self._last_stamp_ns = None
        self._last_size = None
        self._last_epoch = self.pose_buffer.epoch
        self._last_jumps = self.pose_buffer.jumps
        self._keyframe_meta: collections.OrderedDict = collections.OrderedDict()
        self._frame_meta: collections.OrderedDict = collections.OrderedDict()
        self._worker = threading.Thread(target=self._work, name='dpv_sensor_worker', daemon=True)
        self._worker.start()
        # on the steady clock: diagnostics keep coming while sim time (use_sim_time) is paused or not yet published
        self.create_timer(cfg['diagnostics_period'], self._publish_diagnostics,
                          clock=Clock(clock_type=ClockType.STEADY_TIME))
        self._runtime_params = RuntimeParameters(self, cfg, self._apply_parameters)

        log.info(
            f"starting (building the estimator): preset={cfg['preset']} device={cfg['device']}"
            f" cpu_precision={cfg['cpu_precision']} measurement={cfg['measurement']} "
            f"filter={cfg['filter_mode']} readout={cfg['depth_readout']} confidence={cfg['confidence']}"
            f"{' ' + format(cfg['confidence_ratio'], 'g') if cfg['confidence'] == 'ratio' else ''} "
            f"odometry={cfg['odometry']} "
            f"processing={cfg['processing_width']}x{cfg['processing_height']} "
            f"input QoS={cfg['input_reliability']}/{cfg['input_depth']} "
            f"image='{self.sub_image.topic_name}' camera_info="
            f"'{self.sub_info.topic_name if self.sub_info else 'parameters'}' "
            f"odom='{self.sub_odom.topic_name if self.sub_odom else 'none'}'")

    # ------------------------------------------------------------------------------------------ input QoS
    sub_image = property(lambda self: self._input_subs['image'])
    sub_info = property(lambda self: self._input_subs.get('camera_info'))
    sub_odom = property(lambda self: self._input_subs.get('odom'))

    def _subscribe_input(self, topic: str, reliability: str) -> None:
        """(Re)create the subscription of input `topic` with `reliability`; the image subscription also counts the
        samples the middleware reports lost (where it reports them: Fast DDS does for best-effort readers)."""
        old = self._input_subs.pop(topic, None)
        if old is not None:
            self.destroy_subscription(old)
        policy = {'best_effort': ReliabilityPolicy.BEST_EFFORT, 'reliable': ReliabilityPolicy.RELIABLE}[reliability]
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=self.config['input_depth'], reliability=policy,
                         durability=DurabilityPolicy.VOLATILE)
        incompatible = self._qos_events(topic, subscription=True).incompatible_qos
        # DDS "subscription matched": a publisher the graph lists is not necessarily matched by this reader yet,
        # and what it sends before the match is lost (volatile); a new subscription starts unmatched
        self._input_matched[topic] = 0

        def on_matched(info, topic=topic) -> None:
            self._input_matched[topic] = int(info.current_count)
        lost = None
        if topic == 'image':
            lost = lambda info: self.stream_loss.on_rmw_lost(int(info.total_count_change))  # noqa: E731
        events = SubscriptionEventCallbacks(incompatible_qos=incompatible, matched=on_matched, message_lost=lost)
        msg_type, callback = self._inputs[topic]
        self._input_subs[topic] = self.create_subscription(msg_type, self._topic(topic), callback, qos,
                                                           event_callbacks=events)
        self._input_reliability[topic] = reliability

    def _adapt_input_qos(self) -> None:
        """input_reliability auto: follow what the publishers of each input offer (transport.choose_reliability):
        reliable while every publisher is reliable (lost samples are repaired), else best effort."""
        for topic, sub in list(self._input_subs.items()):
            try:
                infos = self.get_publishers_info_by_topic(sub.topic_name)
            except Exception:   # the graph is not available (shutting down): try again next time
                continue
            offered = ['reliable' if i.qos_profile.reliability == ReliabilityPolicy.RELIABLE else 'best_effort'
                       for i in infos]
            want = choose_reliability('auto', offered)
            if want != self._input_reliability[topic]:
                self.get_logger().info(f"input {sub.topic_name}: publishers offer {', '.join(sorted(set(offered)))}"
                                       f'; subscribing {want}')
                self._subscribe_input(topic, want)

    # ------------------------------------------------------------------------------------------ construction
    def _qos_events(self, topic: str, subscription: bool):
        """Event callbacks that count and report incompatible QoS on `topic` (a peer whose QoS cannot match:
        nothing flows between the two, so it is worth a warning)."""
        def on_incompatible(info, topic=topic, role='subscription' if subscription else 'publisher') -> None:
            self.qos_incompatible[topic] += max(1, int(getattr(info, 'total_count_change', 1)))
            kind = getattr(info, 'last_policy_kind', '?')
            policy = getattr(kind, 'name', str(kind))
            self.faults.report(INCOMPATIBLE_QOS, f"incompatible QoS on '{topic}' ({policy}): a peer of this {role} "
                               'cannot match it and receives or sends nothing (e.g. a best-effort subscriber of a '
                               'reliable-only topic; see input_reliability / output_reliability)',
                               key=f'{INCOMPATIBLE_QOS}:{topic}')
        if subscription:
            return SubscriptionEventCallbacks(incompatible_qos=on_incompatible)
        return PublisherEventCallbacks(incompatible_qos=on_incompatible)

    def _publisher(self, msg_type, topic: str, qos):
        return self.create_publisher(msg_type, self._topic(topic), qos,
                                     event_callbacks=self._qos_events(topic, subscription=False))

    def _topic(self, name: str) -> str:
        """The topic name of `name`: a camera_info or transport follows its remapped image topic (topic_names)."""
        return topic_name(name, lambda topic, expand: self.resolve_topic_name(topic, only_expand=expand))

    def _make_pipeline(self) -> Pipeline:
        try:
            return Pipeline(EstimatorConfig.from_params(self.config))
        except Exception as exc:
            raise StartupError(f'cannot build the estimator: {type(exc).__name__}: {exc}') from exc

    def _build(self) -> bool:
        """Worker start: the pipeline (pose source and estimator). On failure the node reports a fatal error:
        ``failed`` is set and the spin loop in :func:`run` stops (exit code 2 with the reason). The worker never
        shuts the context down itself: the main thread owns it."""
        try:
            pipeline = self._make_pipeline()
        except Exception as exc:
            self.fatal_error = str(exc) if isinstance(exc, StartupError) else \
                f'cannot start: {type(exc).__name__}: {exc}'
            self.get_logger().error(self.fatal_error)
            self.failed.set()
            return False
        with self._estimator_lock:
            self.pipeline = pipeline
        st = pipeline.status
        self.get_logger().info(
            f"ready: measurement={st.get('measurement')} ({st.get('measurement_reason')}) "
            f"device={st.get('device')} filter={st.get('filter_mode')} window={st.get('window_mode')} "
            f"planes={st.get('num_planes')} depth range={st.get('depth_range')}")
        return True

    def _apply_parameters(self, values: dict, changes: dict) -> None:
        """Accepted runtime parameter changes (params.RUNTIME): the node reads its settings from self.config at use;
        the estimator's are set on the running pipeline (a pipeline built later takes them from self.config)."""
        with self._estimator_lock:
            self.config = values
            if self.pipeline is not None:
                self.pipeline.apply_settings(changes)

    def close(self) -> bool:
        """Stop the worker and release resources before the node is destroyed; True when the worker stopped."""
        self._stop.set()
        self._mailbox.close()
        with self._inputs_cv:
            self._inputs_cv.notify_all()
        if self._worker.is_alive():
            self._worker.join(timeout=10.0)
        self._log_bridge.detach()
        return not self._worker.is_alive()

    # ------------------------------------------------------------------------------------------ callbacks
    def _on_image(self, msg) -> None:
        self.n_received += 1
        if self.tf is not None:
            self.tf.frames(image_frame=msg.header.frame_id or self.config['frame_id'])
        self._last_image_mono = time.monotonic()
        if self._first_image_mono is None:
            self._first_image_mono = self._last_image_mono
        self.in_rate.tick(self._last_image_mono)
        try:
            stamp_ns = M.stamp_to_ns(msg.header.stamp)
        except Exception:   # a malformed header is reported by the worker; no gap to measure here
            stamp_ns = None
        last, self._last_received_stamp_ns = self._last_received_stamp_ns, stamp_ns
        gap_ns = stamp_ns - last if stamp_ns is not None and last is not None and stamp_ns > last else None
        if not msg.header.frame_id:
            self._on_empty_frame_id(stamp_ns)
        # lost images, stamp jumps and unusable images: judged here, before the mailbox (dpv_sensor.ros.receipt)
        item = self._receipt.image(msg, stamp_ns, gap_ns, time.monotonic(), time.time_ns())
        if item is not None and self._mailbox.put(item):
            with self._stats_lock:
                self.dropped[BUSY] += 1
            self.faults.report(BUSY, 'estimator busy: dropping an older image that was still waiting (newest wins; '
                               'the count is in /diagnostics)', level='info', count=False, period_s=60.0)

    def _on_empty_frame_id(self, stamp_ns) -> None:
        """An image without header.frame_id: the outputs use the frame_id parameter (warned once, every one counted)."""
        if self.faults.counts[EMPTY_FRAME_ID] == 0:
            at = f' (first at {stamp_ns / NS:.3f} s)' if stamp_ns is not None else ''
            self.faults.report(EMPTY_FRAME_ID, f"images arrive with an empty header.frame_id{at}; the outputs use the "
                               f"frame_id parameter '{self.config['frame_id']}' (the camera driver should set its "
                               'optical frame; this is not logged again, faults.empty_frame_id counts them)')
        else:
            self.faults.count(EMPTY_FRAME_ID)

    def _on_camera_info(self, msg) -> None:
        try:
            K, size = M.camera_info_to_K(msg)
        except M.BadCameraInfo as exc:
            self.faults.report(BAD_CAMERA_INFO, f'ignoring camera_info on {self.sub_info.topic_name}: {exc}')
            return
        rect = None
        if M.has_distortion(msg):
            try:
                rect = self._rectifiers.for_camera_info(msg)
            except UnsupportedDistortion as exc:
                self.faults.report(UNSUPPORTED_DISTORTION, f'cannot rectify the images of camera_info on '
                                   f'{self.sub_info.topic_name}: {exc}; images are used as they are (depth is less '
                                   'accurate towards the borders)', period_s=60.0)
            if rect is not None:
                K = np.array(rect.K, dtype=np.float64)
        with self._inputs_cv:
            self._K = (K, size)
            self._rectifier = rect
            self._inputs_cv.notify_all()

    def _on_odom(self, msg) -> None:
        stamp_ns = M.stamp_to_ns(msg.header.stamp)
        try:
            T = M.odometry_to_matrix(msg)
        except M.BadOdometry as exc:
            self.faults.report(NAN_ODOMETRY, f'ignoring odometry at {stamp_ns / NS:.3f} s: {exc}; images '
                               'interpolated across it are dropped')
            T = None
        self._odom_frame = self._odom_frames.update(msg.header.frame_id, stamp_ns)
        if self.tf is not None and msg.child_frame_id:
            self.tf.frames(odom_child_frame=msg.child_frame_id)
        jumps, conflicts = self.pose_buffer.jumps, self.pose_buffer.conflicts
        cleared = self.pose_buffer.add(stamp_ns, T)
        self.pose_covariance.add(stamp_ns, M.odometry_covariance(msg))
        if self.pose_buffer.conflicts != conflicts:
            self.faults.report(ODOM_CONFLICT, f'{self.pose_buffer.last_conflict}; keeping the first (two odometry '
                               'sources publishing on one topic?)')
        if cleared and self.pose_buffer.jumps != jumps:
            self.faults.report(ODOM_JUMP, f'{cleared}: images before it are dropped and the estimator restarts '
                               '(relocalisation or loop closure in the odometry frame?)')
        elif cleared:
            self.faults.report(TIME_BACKWARDS, f'time went backwards: {cleared} (bag restarted or simulator reset?)',
                               key='time_backwards:odometry')
        with self._inputs_cv:
            self._inputs_cv.notify_all()

    # ------------------------------------------------------------------------------------------ worker
    def _work(self) -> None:
        if not self._build():
            return
        while not self._stop.is_set():
            item = self._mailbox.take(timeout=0.2)
            if item is None:
                continue
            try:
                self._process(item)
            except Exception as exc:   # the worker must survive anything
                self.faults.report(INTERNAL_ERROR, f'unexpected error while processing an image: '
                                   f'{type(exc).__name__}: {exc}\n{traceback.format_exc()}', level='error')

    def _drop(self, reason: str) -> None:
        with self._stats_lock:
            self.dropped[reason] += 1

    def _reset_estimator(self, reason: str) -> None:
        self._node_resets += 1
        with self._estimator_lock:
            try:
                self.pipeline.reset(reason)
            except Exception as exc:
                self.get_logger().error(f'pipeline reset failed ({type(exc).__name__}: {exc}); rebuilding it')
                self.pipeline = self._make_pipeline()
        self._forget()

    def _forget(self) -> None:
        """The node's own stream state after a restart: the carried image gap and the recent frame headers."""
        self._gap_carry_ns = None
        self._loss_carry = []
        self._keyframe_meta.clear()
        self._frame_meta.clear()

    def _wait_for_inputs(self, item: Incoming, stamp_ns: int):
        """Wait (at most odom_wait_timeout after the image arrived) for camera_info and a pose at `stamp_ns`.

        Returns (K, camera_info size, T_world_cam | None, None) when both are there, else (None, None, None, why):
        why is None when no camera_info has arrived, else the PoseQuery whose reason ('future' once the timeout
        passed, 'gap', 'too old', 'nan') and detail say why there is no pose.
        """
        cfg = self.config
        deadline = item.receipt_mono + cfg['odom_wait_timeout']
        need_pose = cfg['odometry'] == 'topic'
        while True:
            with self._inputs_cv:
                K = self._K
            query = self.pose_buffer.pose_at(stamp_ns) if need_pose else None
            if K is not None and (not need_pose or query.ok):
                return K[0], K[1], (query.T_world_cam_44 if need_pose else None), None
            if K is not None and need_pose and query.reason != 'future':
                return None, None, None, query          # waiting cannot help (gap, too old, invalid odometry)
            if time.monotonic() >= deadline or self._stop.is_set():
                return None, None, None, (query if K is not None else None)
            with self._inputs_cv:
                self._inputs_cv.wait(min(max(deadline - time.monotonic(), 0.0), 0.05))

    def _process(self, item: Incoming) -> None:
        """One image, in named steps; each step reports and counts its own drops and returns None for them."""
        stamp_ns = M.stamp_to_ns(item.msg.header.stamp)
        # the stream's longest image gap since the last push: images dropped here (bad input, no pose) count too
        self._gap_carry_ns = max_gap(self._gap_carry_ns, item.gap_ns)
        self._loss_carry.extend(item.loss_gaps)
        rgb = self._decode(item.msg, stamp_ns)
        if rgb is None or not self._check_continuity(stamp_ns, (rgb.shape[1], rgb.shape[0])):
            return
        inputs = self._camera_and_pose(item, stamp_ns, (rgb.shape[1], rgb.shape[0]))
        if inputs is None:
            return
        rgb = self._rectify(rgb, stamp_ns)
        out = self._estimate(item, stamp_ns, rgb, *inputs)
        if out is not None:
            self._publish_output(out, rgb, stamp_ns)

    def _rectify(self, rgb, stamp_ns: int):
        """The image undistorted with the current camera_info's maps (as it is without distortion)."""
        with self._inputs_cv:
            rect = self._rectifier
        if rect is None:
            return rgb
        if (rgb.shape[1], rgb.shape[0]) != rect.size:
            self.faults.report(RECTIFY_SIZE, f'image at {stamp_ns / NS:.3f} s is {rgb.shape[1]}x{rgb.shape[0]} but '
                               f'the distorted camera_info is for {rect.size[0]}x{rect.size[1]}; used as it is')
            return rgb
        return rect.rectify(rgb)

    def _decode(self, msg, stamp_ns: int):
        """The image as HxWx3 uint8 RGB, or None (unsupported encoding, inconsistent image)."""
        try:
            return M.image_to_rgb(msg)
        except M.UnsupportedEncoding as exc:
            self._drop(UNSUPPORTED_ENCODING)
            self.faults.report(UNSUPPORTED_ENCODING, f'dropping image at {stamp_ns / NS:.3f} s: {exc}')
        except M.BadImage as exc:
            self._drop(BAD_IMAGE)
            self.faults.report(BAD_IMAGE, f'dropping image at {stamp_ns / NS:.3f} s: {exc}')
        return None

    def _check_continuity(self, stamp_ns: int, size) -> bool:
        """The stream rules of ``continuity`` on the received images (before the pose lookup: a stream that went
        backwards restarts the odometry buffer too). False: drop the image (a duplicate stamp)."""
        order = continuity.time_order(self._last_stamp_ns, stamp_ns)
        if order == continuity.BACKWARDS:
            last = self._last_stamp_ns
            epoch = self.pose_buffer.epoch
            self.faults.report(TIME_BACKWARDS, f'time went backwards: image stamp {stamp_ns / NS:.3f} s after '
                               f'{last / NS:.3f} s; resetting the estimator and the pose buffer '
                               '(bag restarted or simulator reset?)', key='time_backwards:image')
            if epoch == self._last_epoch:   # odometry has not jumped back (yet): its samples are stale
                self.pose_buffer.clear('image time went backwards')
            self._reset_estimator(continuity.backwards_reason(last / NS, stamp_ns / NS, digits=3))
            self._last_size = None
        elif order == continuity.DUPLICATE:
            self._drop(DUPLICATE_STAMP)
            self.faults.report(DUPLICATE_STAMP, f'dropping image at {stamp_ns / NS:.3f} s: same stamp as the '
                               'previous image')
            return False
        self._last_stamp_ns = stamp_ns
        self._last_epoch = self.pose_buffer.epoch
        changed = continuity.size_change(self._last_size, size)
        if changed is not None:
            change = f'{self._last_size[0]}x{self._last_size[1]}->{size[0]}x{size[1]}'
            self.faults.report(SIZE_CHANGE, f'{changed}; resetting the estimator', key=f'{SIZE_CHANGE}:{change}')
            self._reset_estimator(changed)
        self._last_size = size
        return True

    def _camera_and_pose(self, item: Incoming, stamp_ns: int, size):
        """(K of the image size, odometry pose or None without odometry), or None when the image must be dropped
        (no camera_info yet, no odometry in time, an odometry gap ...). Resets on an odometry teleport."""
        K, info_size, pose, why = self._wait_for_inputs(item, stamp_ns)
        if K is None:
            if why is None:
                self._drop(NO_CAMERA_INFO)
                where = self.sub_info.topic_name if self.sub_info else 'parameters'
                self.faults.report(NO_CAMERA_INFO, f'no camera_info received yet on {where}; waiting '
                                   '(images are dropped until it arrives)')
            elif why.reason == 'future':
                self._drop(ODOM_TIMEOUT)
                self.faults.report(ODOM_TIMEOUT, f'dropping image at {stamp_ns / NS:.3f} s: no odometry at or after '
                                   f"its stamp within odom_wait_timeout {self.config['odom_wait_timeout']:g} s "
                                   f'({why.detail})')
            else:
                kind, label = {'gap': (ODOM_GAP, 'odometry gap'), 'too old': (ODOM_TOO_OLD, 'odometry too old'),
                               'nan': (ODOM_INVALID, 'invalid odometry around the image')}[why.reason]
                self._drop(kind)
                self.faults.report(kind, f'dropping image at {stamp_ns / NS:.3f} s ({label}): {why.detail}')
            return None
        if info_size != (0, 0) and info_size != size:
            self.faults.report(CAMERA_INFO_MISMATCH, f'camera_info is for {info_size[0]}x{info_size[1]} but the image '
                               f'is {size[0]}x{size[1]}; scaling K to the image size')
            K = M.scale_K(K, info_size, size)
        if pose is not None and self.pose_buffer.jumps != self._last_jumps:
            # the pose comes from after an odometry teleport: the belief is in the old frame
            self._last_jumps = self.pose_buffer.jumps
            self._reset_estimator('odometry jumped')
        return K, pose

    def _estimate(self, item: Incoming, stamp_ns: int, rgb, K, pose):
        """Push the frame through the pipeline; the output that became ready, or None."""
        frame_id = item.msg.header.frame_id or self.config['frame_id']
        stamp_s = stamp_ns / NS
        meta = _FrameMeta(stamp_ns, frame_id, rgb, K, rgb.shape[1], rgb.shape[0], item.receipt_mono, item.receipt_ns)
        gap_ns = self._stream_gap_ns(item)
        frame = Frame(stamp=stamp_s, image=rgb, K_33=K, T_world_cam_44=pose, frame_id=frame_id,
                      sensor_gap_s=None if gap_ns is None else gap_ns / NS,
                      pose_covariance_66=self.pose_covariance.at(stamp_ns) if pose is not None else None)
        t0 = time.perf_counter()
        with self._estimator_lock:
            try:
                result = self.pipeline.push(frame)
            except Exception as exc:
                result = None
                self._on_estimator_exception(exc)
        if result is not None and result.drop == DEGENERATE:
            self._gap_carry_ns = max_gap(self._gap_carry_ns, gap_ns)    # the stream state is untouched
            self._on_degenerate(stamp_s, result.detail)
            return None
        if self._degenerate_run:
            self._degenerate_episode_end(stamp_s)
        if result is not None and result.drop == VO_LOST:
            self._drop(VO_LOST)
            self.faults.report(VO_LOST, f'visual odometry lost at {stamp_s:.3f} s: {result.detail}; '
                               'resetting the estimator')
            self._node_resets += 1
            self._forget()
            return None
        is_keyframe = result is not None and result.is_keyframe
        self._last_push_ms = (time.perf_counter() - t0) * 1000.0
        self.process_ms.append(self._last_push_ms)
        if is_keyframe:
            self.keyframe_ms.append(self._last_push_ms)
            self._last_keyframe_ms = self._last_push_ms
        self.n_processed += 1
        self._remember(stamp_s, meta, is_keyframe)
        return None if result is None else result.output

    def _stream_gap_ns(self, item: Incoming) -> int | None:
        """The camera stream's longest gap since the last push (Frame.sensor_gap_s), taking the carry: intervals with
        images lost in transport count as one period when the middleware reported them lost, for which an image
        waits up to LOSS_REPORT_WAIT_S after its receipt."""
        pending, self._loss_carry = self._loss_carry, []
        deadline = item.receipt_mono + LOSS_REPORT_WAIT_S
        while any(not g.settled for g in pending) and time.monotonic() < deadline and not self._stop.is_set():
            time.sleep(0.005)
        gap_ns, self._gap_carry_ns = camera_gap_ns(self._gap_carry_ns, pending), None
        return gap_ns

    def _on_degenerate(self, stamp_s: float, reason: str) -> None:
        """A degenerate image (no texture to measure depth from): dropped and counted (dropped.degenerate_image);
        one log line when a run of them starts, one when it ends (rate-limited per kind, black / saturated / flat /
        noise: a flickering camera is summarised, not logged at its frame rate)."""
        self._drop(DEGENERATE)
        if self._degenerate_run == 0:
            self.n_degenerate_episodes += 1
            self._degenerate_reason = reason
            self.faults.report(DEGENERATE, f'degenerate images from {stamp_s:.3f} s on ({reason}): dropped, no depth '
                               'published until they carry texture again (lens covered, exposure or a broken '
                               'driver?)', count=False, key=f'{DEGENERATE}:{reason.split(":")[0]}')
        self._degenerate_run += 1

    def _degenerate_episode_end(self, stamp_s: float) -> None:
        n, self._degenerate_run = self._degenerate_run, 0
        self.faults.report(DEGENERATE, f'degenerate images ended at {stamp_s:.3f} s: {n} dropped '
                           f'({self._degenerate_reason})', count=False, level='info',
                           key=f'{DEGENERATE}:end:{self._degenerate_reason.split(":")[0]}')

    def _publish_output(self, out, rgb, stamp_ns: int) -> None:
        try:
            self._publish(out, current=(stamp_ns / NS, rgb))
        except Exception as exc:
            self.faults.report(PUBLISH_ERROR, f'could not publish the output for {out.stamp:.3f} s: '
                               f'{type(exc).__name__}: {exc}', level='error')

    def _on_estimator_exception(self, exc: Exception) -> None:
        first = self.faults.counts[ESTIMATOR_EXCEPTION] == 0
        text = f'exception inside the estimator ({type(exc).__name__}: {exc}); resetting it and going on'
        if first:
            text += '\n' + traceback.format_exc()
        self.faults.report(ESTIMATOR_EXCEPTION, text, level='error')
        self._reset_estimator(f'exception: {type(exc).__name__}: {exc}')

    def _remember(self, stamp_s: float, meta: '_FrameMeta', is_keyframe: bool) -> None:
        """Keep the headers (and, for keyframes, the images) of recent frames: a centered window publishes a
        keyframe's output two keyframes later and it must carry that frame's exact header."""
        window = int(getattr(getattr(self.pipeline, 'config', None), 'window_size', 5))
        store, cap = (self._keyframe_meta, 2 * window + 6) if is_keyframe else (self._frame_meta, 8)
        if not is_keyframe:
            meta = _FrameMeta(**{**meta.__dict__, 'rgb': None})
        store[stamp_s] = meta
        while len(store) > cap:
            store.popitem(last=False)

    def _lookup(self, stamp_s: float) -> _FrameMeta | None:
        meta = self._keyframe_meta.get(stamp_s) or self._frame_meta.get(stamp_s)
        if meta is None:   # tolerate a float round trip inside the estimator
            for store in (self._keyframe_meta, self._frame_meta):
                for k, m in store.items():
                    if abs(k - stamp_s) < 1e-6:
                        return m
        return meta

    def _publish(self, out, current=None) -> None:
        """Publish one DepthOutput with the exact header of the input frame it belongs to.

        current: (stamp in s, rgb) of the frame just pushed (its colours when the output is for it)."""
        cfg = self.config
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
        conf = np.asarray(out.confidence_hw, dtype=np.float32)     # depth below min_confidence: NaN (estimator)
        h, w = depth.shape
        K_out = self._output_K(out, meta, (w, h))
        rgb = None
        if rgb_src is not None:
            # the colour image at the output size (INTER_AREA, as the output K is the input K scaled to that size)
            rgb = rgb_src if rgb_src.shape[:2] == (h, w) else cv2.resize(rgb_src, (w, h), interpolation=cv2.INTER_AREA)
        info = M.K_to_camera_info(K_out, w, h, header)     # every output's camera_info: K of this size, D zero
        self.pub_depth.publish(M.depth_to_image(depth, header, encoding=cfg['depth_encoding']))
        self.pub_depth_info.publish(info)
        if rgb is not None:
            self.pub_rgb.publish(M.rgb_to_image(rgb, header))
            self.pub_rgb_info.publish(info)
        else:
            self.faults.report(MISSING_RGB, f'no colour image kept for the output at {out.stamp:.3f} s; rgb/image '
                               'skipped', level='error')
        self.pub_conf.publish(M.confidence_to_image(conf, header))
        self.pub_conf_info.publish(info)
        if self.pub_compressed is not None:
            self.pub_compressed.publish(M.depth_to_compressed_depth(depth, header, encoding=cfg['depth_encoding']))
        if self.pub_points.get_subscription_count() > 0 and rgb is not None:
            self._publish_points(depth, rgb, K_out, header, meta.stamp_ns)
        if self.pub_pose is not None and out.T_world_cam_44 is not None:
            self.pub_pose.publish(M.matrix_to_pose_stamped(out.T_world_cam_44, M.make_header(meta.stamp_ns,
                                                                                             self._odom_frame)))
            if self.tf is not None:
                self.tf.publish_refined(out.T_world_cam_44, meta.stamp_ns, self._odom_frame, meta.frame_id)
        reset_reason = getattr(out, 'reset_reason', None)
        if reset_reason and not (self.n_published == 0 and reset_reason == 'first frame'):
            self.n_output_resets += 1
            self._last_output_reset = f'{out.stamp:.3f} s: {reset_reason}'
            self.get_logger().info(f'output for {out.stamp:.3f} s follows a filter restart: {reset_reason}')
        now_ns = self.get_clock().now().nanoseconds     # the node's clock: ROS time with use_sim_time
        self.n_published += 1
        self.n_keyframes_published += int(bool(out.is_keyframe))
        self.out_rate.tick()
        self.latency_ms.append((time.monotonic() - meta.receipt_mono) * 1000.0)
        age = plausible_age_ms(now_ns, meta.stamp_ns)
        if age is None:
            self.n_age_implausible += 1
        else:
            self.age_ms.append(age)

    def _publish_points(self, depth, rgb, K, header, stamp_ns: int) -> None:
        """The organised cloud (every points_decimation-th pixel), at most points_max_rate per second of image
        time: an output closer than 1/rate to the previous cloud's stamp is skipped and counted."""
        max_rate = self.config['points_max_rate']
        last = self._last_points_stamp_ns
        if max_rate > 0 and last is not None and 0 <= stamp_ns - last < NS / max_rate:
            self.n_points_skipped += 1
            return
        self._last_points_stamp_ns = stamp_ns
        self.pub_points.publish(M.depth_to_pointcloud_decimated(depth, rgb, K, header,
                                                                decimation=self.config['points_decimation']))
        self.n_points += 1
        self.points_rate.tick()

    def _output_K(self, out, meta: _FrameMeta, out_wh) -> 'np.ndarray':
        """K of the output image: the input K scaled (in float64) from the input size to the output size. The
        estimator's own K_33 (computed in float32 on its device) must agree; if it does not, it is used as is."""
        K_est = np.asarray(out.K_33, dtype=np.float64)
        in_wh = (meta.in_w, meta.in_h)
        K = np.array(meta.K_in, dtype=np.float64) if in_wh == tuple(out_wh) else M.scale_K(meta.K_in, in_wh, out_wh)
        if not np.allclose(K, K_est, rtol=1e-4, atol=1e-3):
            self.faults.report('output_K_mismatch', f'estimator output K {K_est.round(3).tolist()} differs from the '
                               f'input K scaled to {out_wh[0]}x{out_wh[1]} ({K.round(3).tolist()}); publishing the '
                               "estimator's", level='warn', count=False)
            return K_est
        return K

    # ------------------------------------------------------------------------------------------ diagnostics
    def diagnostics_values(self) -> dict:
        """Everything /diagnostics reports, as a flat {key: value} dict."""
        with self._stats_lock:
            dropped = dict(self.dropped)
        try:
            st = dict(self.pipeline.status) if self.pipeline is not None else \
                {'measurement': 'starting', 'tracking': 'building the estimator'}
        except Exception as exc:
            st = {'status_error': str(exc)}
        lat = list(self.latency_ms)
        age = list(self.age_ms)
        proc = list(self.process_ms)
        kf = list(self.keyframe_ms)
        values = {
            'input_rate_hz': round(self.in_rate.rate(), 3),
            'output_rate_hz': round(self.out_rate.rate(), 3),
            'frames_received': self.n_received,
            'frames_processed': self.n_processed,
            'outputs_published': self.n_published,
            'keyframes_published': self.n_keyframes_published,
            'point_clouds_published': self.n_points,
            'latency_ms_median': round(float(np.median(lat)), 1) if lat else 'n/a',
            'latency_ms_p95': round(float(np.percentile(lat, 95)), 1) if lat else 'n/a',
            # on the node's clock, for stamps within an hour of it
            'stamp_age_ms_median': round(float(np.median(age)), 1) if age else 'n/a',
            'stamp_age_implausible': self.n_age_implausible,
            'depth_rate_hz': round(self.out_rate.mean_rate(self._first_image_mono), 3),
            'expected_depth_rate_hz': self.config['expected_depth_rate'],
            'points_rate_hz': round(self.points_rate.mean_rate(self._first_image_mono), 3),
            'expected_points_rate_hz': self.config['expected_points_rate'],
            'points_skipped_rate_cap': self.n_points_skipped,
            'processing_ms_median': round(float(np.median(proc)), 1) if proc else 'n/a',
            'keyframe_ms_median': round(float(np.median(kf)), 1) if kf else 'n/a',
            'keyframe_ms_last': round(self._last_keyframe_ms, 1) if self._last_keyframe_ms is not None else 'n/a',
            'dropped_total': sum(dropped.values()),
        }
        for reason, n in sorted(dropped.items()):
            values[f'dropped.{reason}'] = n
        values.update(self.stream_loss.counts())          # lost.* (images lost before the callback), input_period_ms
        values['degenerate_episodes'] = self.n_degenerate_episodes
        values['odometry_duplicates'] = self.pose_buffer.duplicates     # identical repeats, ignored
        for kind, n in sorted(self.faults.counts.items()):
            values[f'faults.{kind}'] = n
        values['filter_resets'] = st.get('resets', self._node_resets)
        values['last_reset_reason'] = st.get('last_reset_reason') or ''
        values['output_resets'] = self.n_output_resets
        values['last_output_reset'] = self._last_output_reset
        values['measurement_model'] = st.get('measurement', 'unknown')
        values['measurement_reason'] = st.get('measurement_reason', '')
        values['device'] = st.get('device', self.config['device'])
        values['precision'] = st.get('precision', '')
        values['filter_mode'] = st.get('filter_mode', self.config['filter_mode'])
        values['tracking'] = st.get('tracking', '')
        values['pose_uncertainty'] = _pose_uncertainty_text(st.get('pose_uncertainty'), self.config['pose_uncertainty'])
        values['estimator_keyframes'] = st.get('keyframes', '')
        values['estimator_outputs'] = st.get('outputs', '')
        values['estimator_dropped'] = st.get('frames_dropped', '')
        values['estimator_last_drop_reason'] = st.get('last_drop_reason') or ''
        notes = st.get('notes') or []
        if notes:
            values['estimator_notes'] = ' | '.join(notes)
        if 'pose_refinement_tracking' in st:
            values['pose_refinement_tracking'] = st['pose_refinement_tracking']
            values['pose_refinement_fallbacks'] = st.get('pose_refinement_fallbacks', 0)
            values['pose_refinement_last_fallback'] = st.get('last_pose_refinement_fallback_reason') or ''
        values['pose_buffer_size'] = len(self.pose_buffer)
        values['tf'] = self.tf.status() if self.tf is not None else 'off'
        rect = self._rectifier
        values['rectification'] = 'off' if rect is None else \
            f'on ({rect.calibration.model}, K fx={rect.K[0, 0]:.2f} fy={rect.K[1, 1]:.2f})'
        for topic, n in sorted(self.qos_incompatible.items()):
            values[f'qos_incompatible.{topic}'] = n
        # publishers of the inputs that this node's subscriptions have matched (listed in the graph and matched by
        # the DDS reader: 0 means nothing arrives yet)
        for topic, sub in self._input_subs.items():
            values[f'publishers.{topic}'] = min(sub.get_publisher_count(), self._input_matched.get(topic, 0))
        for topic, reliability in self._input_reliability.items():
            values[f'input_qos.{topic}'] = reliability
        return values

    def _drop_share_status(self, values: dict):
        """(level, problem or '') from the share of the images of the last rate_window that were lost in transport
        (lost.transport) or rejected as faulty (dropped.* other than busy: images replaced while the estimator
        was busy are the normal regime of a slow machine, reported but not warned about). Judged from 5 images
        on. Adds drop_share_window to `values`."""
        cfg = self.config
        now = time.monotonic()

        def number(v):
            try:
                return float(v)
            except (TypeError, ValueError):
                return 0.0
        faulty = sum(number(v) for k, v in values.items() if k.startswith('dropped.') and k != f'dropped.{BUSY}')
        lost = number(values.get('lost.transport', 0))     # every image lost before the callback (stream_loss)
        hist = self._share_history
        hist.append((now, self.n_received, faulty, lost))
        while len(hist) > 1 and now - hist[1][0] >= cfg['rate_window']:
            hist.popleft()
        _t0, rec0, faulty0, lost0 = hist[0]
        seen = (self.n_received - rec0) + (lost - lost0)
        bad = (faulty - faulty0) + (lost - lost0)
        share = bad / seen if seen > 0 else 0.0
        values['drop_share_window'] = round(share, 3)
        if seen < 5 or bad <= 0:
            return DiagnosticStatus.OK, ''
        text = (f'{share:.0%} of the last {int(seen)} images lost in transport or rejected as faulty '
                '(see lost.*, dropped.*)')
        if share > cfg['drop_error_share']:
            return DiagnosticStatus.ERROR, text
        if share > cfg['drop_warn_share']:
            return DiagnosticStatus.WARN, text
        return DiagnosticStatus.OK, ''

    def _rate_status(self, values: dict) -> list:
        """Frequency status per output against its expected rate: WARN below expected * (1 - rate_tolerance),
        ERROR when none came in the window; judged once images have arrived for a whole rate_window and while
        they still arrive (a stalled input has its own warning)."""
        cfg = self.config
        first, last = self._first_image_mono, self._last_image_mono
        now = time.monotonic()
        if first is None or now - first < cfg['rate_window'] or now - last > 2.0:
            return []
        out = []
        checks = [('depth/image', values.get('depth_rate_hz', 0.0), cfg['expected_depth_rate'])]
        if self.pub_points.get_subscription_count() > 0:
            checks.append(('depth/points', values.get('points_rate_hz', 0.0), cfg['expected_points_rate']))
        for name, rate, expected in checks:
            if expected > 0 and rate < expected * (1.0 - cfg['rate_tolerance']):
                level = DiagnosticStatus.ERROR if rate == 0 else DiagnosticStatus.WARN
                out.append((level, f'{name} at {rate:.2f} Hz, expected {expected:g} Hz'))
        return out

    def _publish_diagnostics(self) -> None:
        try:
            values = self.diagnostics_values()
        except Exception as exc:
            values = {'error': f'{type(exc).__name__}: {exc}'}
        level, message = DiagnosticStatus.OK, 'ok'
        problems = []
        exceptions = self.faults.counts[ESTIMATOR_EXCEPTION]
        if exceptions > self._last_exception_count:
            level = DiagnosticStatus.ERROR
            problems.append('estimator exceptions')
        self._last_exception_count = exceptions
        # faults that do not drop an image (camera_info, odometry jumps, incompatible QoS ...) warn when new; images
        # lost or rejected count by their share of the recent images (below)
        with self._stats_lock:
            drop_kinds = set(self.dropped)
        total_faults = sum(n for k, n in self.faults.counts.items() if k not in drop_kinds)
        if total_faults > self._last_fault_total:
            level = max(level, DiagnosticStatus.WARN)
            problems.append('input faults (see faults.*)')
        self._last_fault_total = total_faults
        share_level, share_problem = self._drop_share_status(values)
        level = max(level, share_level)
        if share_problem:
            problems.append(share_problem)
        for rate_level, rate_problem in self._rate_status(values):
            level = max(level, rate_level)
            problems.append(rate_problem)
        if str(values.get('measurement_reason', '')).startswith('fallback'):
            level = max(level, DiagnosticStatus.WARN)
            problems.append('network weights missing: classical fallback')
        last_in = self._last_image_mono
        if last_in is None:
            problems.append('no images received yet')
        elif time.monotonic() - last_in > 2.0:
            level = max(level, DiagnosticStatus.WARN)
            problems.append(f'no image for {time.monotonic() - last_in:.1f} s')
        if problems:
            message = '; '.join(problems)
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        name = f"{self.get_fully_qualified_name().lstrip('/')}: depth camera"
        arr.status = [DiagnosticStatus(level=level, name=name, message=message,
                                       hardware_id=f"dpv_sensor ({values.get('device', '?')})",
                                       values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])]
        self.pub_diag.publish(arr)


def _pose_uncertainty_text(last: dict | None, setting: str) -> str:
    """The /diagnostics value of the last keyframe's pose uncertainty: its source and size, or the setting."""
    if setting == 'off' or not last:
        return setting if setting == 'off' else f'{setting} (no keyframe yet)'
    if 'rot_deg_max' not in last:
        return str(last.get('source'))
    return (f"{last['source']}: rotation {last['rot_deg_max']:.3f} deg, translation {last['trans_mm_max']:.2f} mm "
            f"(largest source, per axis), median {last['median_planes']:.2f} planes")


def run(argv: list[str], stop: threading.Event) -> int:
    """Build the node and spin it until ``stop`` is set (SIGINT / SIGTERM, see ``dpv_sensor.ros.entry``) or the worker
    reports that the pipeline cannot be built. Returns the exit code: 0, or 2 for a refused parameter or a failed
    start (with the one message on stderr). Only this thread creates and shuts down the ROS context."""
    from dpv_sensor.ros import entry
    # capped by the entry point before any thread existed (DDS, the worker, OpenMP; see process_memory)
    arenas_note = entry.ARENAS_NOTE
    if arenas_note is None:
        from dpv_sensor.ros.process_memory import limit_malloc_arenas
        arenas_note = limit_malloc_arenas()
    # the node's DDS transport, before rclpy.init (applied by the entry point already; idempotent)
    transport_note = entry.apply_transport_settings()
    if stop.is_set():
        return 0
    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    node = None
    executor = None
    code = 0
    try:
        if stop.is_set():
            return 0
        node = DepthCameraNode()
        node.get_logger().info(arenas_note)
        node.get_logger().info(transport_note)
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        while not stop.is_set() and not node.failed.is_set() and rclpy.ok():
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except P.ParameterError as exc:
        print(f'[{NODE_NAME}] invalid parameter: {exc}', file=sys.stderr)
        code = 2
    except StartupError as exc:
        print(f'[{NODE_NAME}] {exc}', file=sys.stderr)
        code = 2
    finally:
        if executor is not None:
            executor.shutdown()
        if node is not None:
            node.close()
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
    if node is not None and node.fatal_error:
        return 2            # the worker logged it (one ERROR line)
    return code


def main(argv: list[str] | None = None) -> int:
    """The entry point (``dpv_sensor.ros.entry.main``: signal handlers first, then this module)."""
    from dpv_sensor.ros.entry import main as entry_main
    return entry_main(argv, run=run)


if __name__ == '__main__':
    from dpv_sensor.ros.entry import exit_process
    exit_process(main())
