"""`ros2 run dpv_sensor node`: the rclpy adapter of the virtual depth camera.

This module owns ROS plumbing only: parameters, QoS, subscriptions, publishing, diagnostics, signals. The
algorithm lives in dpv_sensor.estimator (Estimator.push(Frame) -> DepthOutput | None); messages are converted by
dpv_sensor.msgs; image poses come from dpv_sensor.pose_buffer.

Topics (relative names, remappable):
  in   image (sensor_msgs/Image rgb8/bgr8/rgba8/bgra8/mono8), camera_info (sensor_msgs/CameraInfo),
       odom (nav_msgs/Odometry) - sensor-data QoS by default (input_reliability, input_depth)
  out  depth/image (32FC1 m, NaN = none | 16UC1 mm, 0 = none), depth/camera_info (K of the output size),
       confidence/image (32FC1 in [0, 1]), points (PointCloud2 XYZRGB, only computed while subscribed),
       pose (PoseStamped, with pose_refinement or odometry none), /diagnostics (DiagnosticArray)
       with publish_tf: /tf_static (base_frame -> image frame, T_base_camera) and /tf (<image frame>_refined,
       with the pose output), tf2_msgs/TFMessage (dpv_sensor.tf_publisher)

Threading: callbacks only store messages. The newest image waits in a one-slot mailbox ("newest wins": an image
that is still waiting when a newer one arrives is dropped and counted) and a worker thread converts it, waits up to
odom_wait_timeout for odometry after its stamp, runs the estimator and publishes. Memory stays flat whatever the
input rate. Dropping is deliberate and does not break the stream: every Frame carries `sensor_gap_s`, the longest
interval between consecutive images the node *received* since the previous frame it pushed (dropped images
included), so the estimator's time-gap reset fires only when the camera stream itself stalled; its jump rules judge
the motion against the elapsed time, so a slow machine that pushes a frame every few seconds keeps its filter.
Every output carries exactly the input image's header (stamp and frame_id). The worker builds the estimator when
the node starts ('ready' is logged once topics and parameters are up, 'estimator ready' once the model is loaded);
if it cannot be built (e.g. measurement=network without weights) the node exits with code 2.
SIGINT / SIGTERM stop the node cleanly (exit 0), also while it is still starting.

Bad input never stops the node: each kind of fault (unsupported encoding, inconsistent image, size change,
missing or zero camera_info, NaN odometry, odometry gap or timeout, time going backwards, an exception inside the
estimator) is counted, reported in /diagnostics and logged with a specific, rate-limited message.
"""
from __future__ import annotations

import argparse
import collections
import logging
import sys
import threading
import time
import traceback
from dataclasses import dataclass

from dpv_sensor import params as P

NODE_NAME = 'dpv_sensor'
NS = 1_000_000_000

# fault kinds (counter names in /diagnostics; each has its own log message)
UNSUPPORTED_ENCODING = 'unsupported_encoding'
BAD_IMAGE = 'bad_image'
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
TIME_BACKWARDS = 'time_backwards'
DUPLICATE_STAMP = 'duplicate_stamp'
ESTIMATOR_EXCEPTION = 'estimator_exception'
VO_LOST = 'visual_odometry_lost'
PUBLISH_ERROR = 'publish_error'
UNKNOWN_OUTPUT = 'unknown_output_stamp'
INTERNAL_ERROR = 'internal_error'
BUSY = 'busy'


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


def _descriptor(spec: P.ParamSpec):
    from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor)
    desc = ParameterDescriptor(name=spec.name, description=spec.description, read_only=True)
    if spec.choices:
        desc.additional_constraints = 'one of: ' + ', '.join(map(str, spec.choices))
    if spec.kind is float and (spec.min_value is not None or spec.max_value is not None):
        desc.floating_point_range = [FloatingPointRange(
            from_value=float(spec.min_value if spec.min_value is not None else -1e300),
            to_value=float(spec.max_value if spec.max_value is not None else 1e300), step=0.0)]
    if spec.kind is int and (spec.min_value is not None or spec.max_value is not None):
        desc.integer_range = [IntegerRange(
            from_value=int(spec.min_value if spec.min_value is not None else -(2 ** 62)),
            to_value=int(spec.max_value if spec.max_value is not None else 2 ** 62), step=1)]
    return desc


def declare_parameters(node) -> dict:
    """Declare every parameter of params.SPECS on `node` and return their validated values."""
    from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
    for spec in P.SPECS:
        try:
            node.declare_parameter(spec.name, spec.default, _descriptor(spec))
        except (InvalidParameterTypeException, InvalidParameterValueException) as exc:
            raise P.ParameterError(f"parameter '{spec.name}' rejected: {exc}") from None
    values = {spec.name: node.get_parameter(spec.name).value for spec in P.SPECS}
    return P.validate(values)


def _node_base():
    from rclpy.node import Node
    return Node


class StartupError(RuntimeError):
    """The node cannot start (e.g. the estimator cannot be built with the given parameters)."""


# --------------------------------------------------------------------------------------------------------------
# small plumbing pieces (no ROS)
# --------------------------------------------------------------------------------------------------------------
class Mailbox:
    """One-slot hand-over from the callback thread to the worker: a newer item replaces a waiting one.

    merge: optional `merge(dropped_item, new_item) -> item` called (under the lock) when a waiting item is replaced,
    so the new item can inherit what the dropped one knew (the node carries the stream's longest image gap)."""

    def __init__(self, merge=None):
        self._item = None
        self._cv = threading.Condition()
        self._merge = merge
        self.replaced = 0
        self.closed = False

    def put(self, item) -> bool:
        """Store `item`; returns True when it replaced (dropped) an item the worker had not taken yet."""
        with self._cv:
            dropped = self._item is not None
            if dropped:
                self.replaced += 1
                if self._merge is not None:
                    item = self._merge(self._item, item)
            self._item = item
            self._cv.notify()
            return dropped

    def take(self, timeout: float):
        """The waiting item (removing it), or None after `timeout` s / when closed."""
        with self._cv:
            if self._item is None and not self.closed:
                self._cv.wait(timeout)
            item, self._item = self._item, None
            return item

    def close(self) -> None:
        with self._cv:
            self.closed = True
            self._cv.notify_all()


class RateMeter:
    """Events per second over a sliding window of monotonic times."""

    def __init__(self, window_s: float = 5.0):
        self.window_s = window_s
        self._t: collections.deque[float] = collections.deque()
        self._lock = threading.Lock()

    def tick(self, t: float | None = None) -> None:
        with self._lock:
            self._t.append(time.monotonic() if t is None else t)
            self._trim()

    def _trim(self):
        now = time.monotonic()
        while self._t and now - self._t[0] > self.window_s:
            self._t.popleft()

    def rate(self) -> float:
        with self._lock:
            self._trim()
            if len(self._t) < 2:
                return 0.0
            span = max(self._t[-1] - self._t[0], 1e-6)
            return (len(self._t) - 1) / span

    def last(self) -> float | None:
        with self._lock:
            return self._t[-1] if self._t else None


class FaultLog:
    """Per-kind counters and rate-limited log messages.

    Messages are limited per key (the kind, or a finer key such as 'image_size_change:640x480->320x240'): at most
    `burst` messages per key in any `period_s` window; the ones held back are counted and the number is appended to
    the next message of that key that gets through.
    """

    def __init__(self, logger, period_s: float = 5.0, burst: int = 3):
        self.logger = logger
        self.period_s = period_s
        self.burst = burst
        self.counts: collections.Counter = collections.Counter()
        self._recent: dict[str, collections.deque] = {}
        self._suppressed: collections.Counter = collections.Counter()
        self._lock = threading.Lock()

    def report(self, kind: str, message: str, level: str = 'warn', count: bool = True, key: str | None = None,
               period_s: float | None = None) -> bool:
        """Count one fault of `kind` and log `message` unless rate-limited; returns True when it was logged.
        `period_s` overrides the limiter window for this key."""
        now = time.monotonic()
        key = key or kind
        period = self.period_s if period_s is None else period_s
        with self._lock:
            if count:
                self.counts[kind] += 1
            recent = self._recent.setdefault(key, collections.deque())
            while recent and now - recent[0] >= period:
                recent.popleft()
            if len(recent) >= self.burst:
                self._suppressed[key] += 1
                return False
            recent.append(now)
            suppressed, self._suppressed[key] = self._suppressed[key], 0
        if suppressed:
            message += f' ({suppressed} more like this were not logged)'
        # one call site per severity: rclpy loggers refuse a severity change at the same call site
        if level == 'error':
            self.logger.error(message)
        elif level == 'info':
            self.logger.info(message)
        else:
            self.logger.warning(message)
        return True


class _LoggerAdapter:
    """A logging.Logger-like front for an rclpy logger (what Estimator(logger=...) expects)."""

    def __init__(self, rcl_logger):
        self._log = rcl_logger

    def debug(self, msg, *args, **kw):
        self._log.debug(str(msg) % args if args else str(msg))

    def info(self, msg, *args, **kw):
        self._log.info(str(msg) % args if args else str(msg))

    def warning(self, msg, *args, **kw):
        self._log.warning(str(msg) % args if args else str(msg))

    warn = warning

    def error(self, msg, *args, **kw):
        self._log.error(str(msg) % args if args else str(msg))

    def exception(self, msg, *args, **kw):
        self.error((str(msg) % args if args else str(msg)) + '\n' + traceback.format_exc())


class _ForwardHandler(logging.Handler):
    """Python logging records of dpv_sensor.* -> the node's rclpy logger."""

    def __init__(self, rcl_logger):
        super().__init__(level=logging.INFO)
        self._log = rcl_logger

    def emit(self, record):
        try:
            msg = f'[{record.name}] {record.getMessage()}'
            if record.levelno >= logging.ERROR:
                self._log.error(msg)
            elif record.levelno >= logging.WARNING:
                self._log.warning(msg)
            else:
                self._log.info(msg)
        except Exception:  # logging must never raise into the algorithm
            pass


def _max_gap(a: int | None, b: int | None) -> int | None:
    """The larger of two image gaps (ns); None = unknown, ignored."""
    return b if a is None else a if b is None else max(a, b)


@dataclass
class _Incoming:
    msg: object          # sensor_msgs/Image as received
    receipt_mono: float  # time.monotonic() at receipt
    receipt_ns: int      # wall clock (ns) at receipt
    gap_ns: int | None = None  # longest stamp interval between consecutive received images up to this one, since
    #                            the previous item the worker took (None: first image, or time went backwards)


def _merge_incoming(dropped: _Incoming, new: _Incoming) -> _Incoming:
    """Mailbox merge: the image replacing a dropped one inherits the dropped one's stream gap."""
    new.gap_ns = _max_gap(dropped.gap_ns, new.gap_ns)
    return new


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
class DepthCameraNode(_node_base()):
    """The virtual depth camera on the ROS graph (parameters, topics, diagnostics)."""

    def __init__(self, **kwargs):
        # everything imported before the node joins the graph, so it is up moments after it is visible
        import numpy as np
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import CameraInfo, Image, PointCloud2
        from nav_msgs.msg import Odometry
        from geometry_msgs.msg import PoseStamped
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue  # noqa: F401
        from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor  # noqa: F401
        from rclpy.exceptions import InvalidParameterTypeException  # noqa: F401

        from dpv_sensor import msgs as M
        from dpv_sensor.frame import Frame  # noqa: F401
        from dpv_sensor.pose_buffer import PoseBuffer, pose7_to_matrix

        super().__init__(NODE_NAME, **kwargs)

        self._np = np
        self._M = M
        self.config = cfg = declare_parameters(self)
        log = self.get_logger()
        self.faults = FaultLog(log)
        self.dropped: collections.Counter = collections.Counter()
        self._stats_lock = threading.Lock()
        self._py_log_handler = _ForwardHandler(log)
        logging.getLogger('dpv_sensor').addHandler(self._py_log_handler)
        logging.getLogger('dpv_sensor').setLevel(logging.INFO)

        # --- the estimator is built by the worker thread (loading weights / CUDA can take seconds; the node
        # meanwhile buffers odometry, keeps the newest image and reports 'starting' in /diagnostics) ----------
        self.pose_refiner = None
        self.visual_odometry = None
        self.estimator = None
        self.fatal_error: str | None = None
        self._estimator_lock = threading.RLock()

        # --- pose buffer and camera intrinsics -------------------------------------------------------------
        self.T_base_camera = pose7_to_matrix(cfg['T_base_camera'])
        self.pose_buffer = PoseBuffer(max_gap_s=cfg['max_odom_gap'], history_s=max(10.0, 4 * cfg['max_odom_gap']),
                                      T_base_camera_44=self.T_base_camera, max_speed=cfg['odom_max_speed'],
                                      max_rate_deg=cfg['odom_max_rate_deg'])
        self._inputs_cv = threading.Condition()      # notified when odometry or camera_info arrives
        self._K = None                                # (K 3x3, (w, h)) from camera_info or the parameters
        if cfg['camera_info_source'] == 'parameters':
            self._K = (np.array([[cfg['fx'], 0.0, cfg['cx']], [0.0, cfg['fy'], cfg['cy']], [0.0, 0.0, 1.0]]),
                       (0, 0))
        self._warned_distortion = False
        self._odom_frame = 'odom'

        # --- QoS, subscriptions, publishers ------------------------------------------------------------------
        rel = {'best_effort': ReliabilityPolicy.BEST_EFFORT, 'reliable': ReliabilityPolicy.RELIABLE}
        in_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=cfg['input_depth'],
                            reliability=rel[cfg['input_reliability']], durability=DurabilityPolicy.VOLATILE)
        out_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=cfg['output_depth'],
                             reliability=rel[cfg['output_reliability']], durability=DurabilityPolicy.VOLATILE)
        self.sub_image = self.create_subscription(Image, 'image', self._on_image, in_qos)
        self.sub_info = None
        if cfg['camera_info_source'] == 'topic':
            self.sub_info = self.create_subscription(CameraInfo, 'camera_info', self._on_camera_info, in_qos)
        self.sub_odom = None
        if cfg['odometry'] == 'topic':
            self.sub_odom = self.create_subscription(Odometry, 'odom', self._on_odom, in_qos)
        self.pub_depth = self.create_publisher(Image, 'depth/image', out_qos)
        self.pub_depth_info = self.create_publisher(CameraInfo, 'depth/camera_info', out_qos)
        self.pub_conf = self.create_publisher(Image, 'confidence/image', out_qos)
        self.pub_points = self.create_publisher(PointCloud2, 'points', out_qos)
        self.pub_pose = None
        if cfg['pose_refinement'] != 'off' or cfg['odometry'] == 'none':
            # the refined pose, or the visual odometry's (the user has no other pose source then), in the odometry
            # frame ('odom' without odometry)
            self.pub_pose = self.create_publisher(PoseStamped, 'pose', out_qos)
        self.pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self.tf = None      # TF output (dpv_sensor.tf_publisher), with publish_tf
        if cfg['publish_tf']:
            try:
                from dpv_sensor.tf_publisher import TfPublisher
                self.tf = TfPublisher(self, self.T_base_camera, base_frame=cfg['base_frame'])
            except ImportError as exc:
                log.error(f'publish_tf is set but tf2_msgs does not import ({exc}); no TF is published '
                          '(make venv generates tf2_msgs; or source a ROS installation that has it)')

        # --- statistics ----------------------------------------------------------------------------------------
        self.in_rate = RateMeter()
        self.out_rate = RateMeter()
        self.latency_ms: collections.deque[float] = collections.deque(maxlen=200)   # receipt -> published
        self.age_ms: collections.deque[float] = collections.deque(maxlen=200)       # header stamp -> published
        self.process_ms: collections.deque[float] = collections.deque(maxlen=200)   # estimator.push, any frame
        self.keyframe_ms: collections.deque[float] = collections.deque(maxlen=50)   # estimator.push, keyframes
        self.n_received = self.n_processed = self.n_published = self.n_keyframes_published = 0
        self.n_points = 0
        self._node_resets = 0
        self._last_fault_total = 0
        self._last_exception_count = 0
        self._started_mono = time.monotonic()
        self._last_image_mono = None
        self._last_push_ms = 0.0

        # --- worker ---------------------------------------------------------------------------------------------
        self._mailbox = Mailbox(merge=_merge_incoming)
        self._last_received_stamp_ns = None   # header stamp of the newest image received (callback thread only)
        self._gap_carry_ns = None             # longest image gap since the last push (worker thread only)
        self._stop = threading.Event()
        self._last_stamp_ns = None
        self._last_size = None
        self._last_epoch = self.pose_buffer.epoch
        self._last_jumps = self.pose_buffer.jumps
        self._keyframe_meta: collections.OrderedDict = collections.OrderedDict()
        self._frame_meta: collections.OrderedDict = collections.OrderedDict()
        self._worker = threading.Thread(target=self._work, name='dpv_sensor_worker', daemon=True)
        self._worker.start()
        self.create_timer(cfg['diagnostics_period'], self._publish_diagnostics)

        log.info(
            f"ready: preset={cfg['preset']} device={cfg['device']}"
            f" cpu_precision={cfg['cpu_precision']} measurement={cfg['measurement']} "
            f"filter={cfg['filter_mode']} readout={cfg['depth_readout']} confidence={cfg['confidence']}"
            f"{' ' + format(cfg['confidence_ratio'], 'g') if cfg['confidence'] == 'ratio' else ''} odometry={cfg['odometry']} "
            f"processing={cfg['processing_width']}x{cfg['processing_height']} "
            f"input QoS={cfg['input_reliability']}/{cfg['input_depth']} "
            f"image='{self.sub_image.topic_name}' camera_info="
            f"'{self.sub_info.topic_name if self.sub_info else 'parameters'}' "
            f"odom='{self.sub_odom.topic_name if self.sub_odom else 'none'}'")

    # ------------------------------------------------------------------------------------------ construction
    def _make_estimator(self):
        from dpv_sensor.estimator import Estimator, EstimatorConfig
        try:
            return Estimator(EstimatorConfig.from_params(self.config), pose_refiner=self.pose_refiner,
                             logger=_LoggerAdapter(self.get_logger()))
        except Exception as exc:
            raise StartupError(f'cannot build the estimator: {type(exc).__name__}: {exc}') from exc

    def _build(self) -> bool:
        """Worker start: pose refiner / visual odometry when asked for, then the estimator. On failure the node
        shuts down (main() exits with code 2 and the reason)."""
        cfg = self.config
        try:
            if cfg['pose_refinement'] == 'window':
                from dpv_sensor.poses import PoseRefinerConfig, WindowPoseRefiner
                self.pose_refiner = WindowPoseRefiner(PoseRefinerConfig.from_params(cfg))
            if cfg['odometry'] == 'none':
                from dpv_sensor.poses import VisualOdometry
                self.visual_odometry = VisualOdometry()
            estimator = self._make_estimator()
        except Exception as exc:
            self.fatal_error = str(exc) if isinstance(exc, StartupError) else \
                f'cannot start: {type(exc).__name__}: {exc}'
            self.get_logger().error(self.fatal_error)
            try:
                self.context.try_shutdown()
            except Exception:
                pass
            return False
        with self._estimator_lock:
            self.estimator = estimator
        st = estimator.status
        self.get_logger().info(
            f"estimator ready: measurement={st.get('measurement')} ({st.get('measurement_reason')}) "
            f"device={st.get('device')} filter={st.get('filter_mode')} window={st.get('window_mode')} "
            f"planes={st.get('num_planes')} depth range={st.get('depth_range')}")
        return True

    def close(self) -> None:
        """Stop the worker and release resources before the node is destroyed."""
        self._stop.set()
        self._mailbox.close()
        with self._inputs_cv:
            self._inputs_cv.notify_all()
        if self._worker.is_alive():
            self._worker.join(timeout=10.0)
        logging.getLogger('dpv_sensor').removeHandler(self._py_log_handler)

    # ------------------------------------------------------------------------------------------ callbacks
    def _on_image(self, msg) -> None:
        self.n_received += 1
        if self.tf is not None:
            self.tf.frames(image_frame=msg.header.frame_id)
        self._last_image_mono = time.monotonic()
        self.in_rate.tick(self._last_image_mono)
        try:
            stamp_ns = self._M.stamp_to_ns(msg.header.stamp)
        except Exception:   # a malformed header is reported by the worker; no gap to measure here
            stamp_ns = None
        last, self._last_received_stamp_ns = self._last_received_stamp_ns, stamp_ns
        gap_ns = stamp_ns - last if stamp_ns is not None and last is not None and stamp_ns > last else None
        if self._mailbox.put(_Incoming(msg, time.monotonic(), time.time_ns(), gap_ns)):
            with self._stats_lock:
                self.dropped[BUSY] += 1
            self.faults.report(BUSY, 'estimator busy: dropping an older image that was still waiting (newest wins; '
                               'the count is in /diagnostics)', level='info', count=False, period_s=60.0)

    def _on_camera_info(self, msg) -> None:
        M = self._M
        try:
            K, size = M.camera_info_to_K(msg)
        except M.BadCameraInfo as exc:
            self.faults.report(BAD_CAMERA_INFO, f'ignoring camera_info on {self.sub_info.topic_name}: {exc}')
            return
        if not self._warned_distortion and M.has_distortion(msg):
            self._warned_distortion = True
            self.get_logger().warning(
                f'camera_info has non-zero distortion ({msg.distortion_model}); images are used as they are '
                '(feed rectified images, e.g. image_proc, for accurate depth)')
        with self._inputs_cv:
            self._K = (K, size)
            self._inputs_cv.notify_all()

    def _on_odom(self, msg) -> None:
        M = self._M
        stamp_ns = M.stamp_to_ns(msg.header.stamp)
        try:
            T = M.odometry_to_matrix(msg)
        except M.BadOdometry as exc:
            self.faults.report(NAN_ODOMETRY, f'ignoring odometry at {stamp_ns / NS:.3f} s: {exc}; images '
                               'interpolated across it are dropped')
            T = None
        self._odom_frame = msg.header.frame_id or self._odom_frame
        if self.tf is not None and msg.child_frame_id:
            self.tf.frames(odom_child_frame=msg.child_frame_id)
        jumps = self.pose_buffer.jumps
        cleared = self.pose_buffer.add(stamp_ns, T)
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
                self.estimator.reset(reason)
            except Exception as exc:
                self.get_logger().error(f'estimator.reset failed ({type(exc).__name__}: {exc}); rebuilding it')
                self.estimator = self._make_estimator()
        if self.pose_refiner is not None:
            self.pose_refiner.reset()
        if self.visual_odometry is not None:
            self.visual_odometry.reset()
        self._gap_carry_ns = None
        self._keyframe_meta.clear()
        self._frame_meta.clear()

    def _wait_for_inputs(self, item: _Incoming, stamp_ns: int):
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

    def _process(self, item: _Incoming) -> None:
        np, M = self._np, self._M
        cfg = self.config
        msg = item.msg
        stamp_ns = M.stamp_to_ns(msg.header.stamp)
        frame_id = msg.header.frame_id
        # the stream's longest image gap since the last push: images dropped here (bad input, no pose) count too
        self._gap_carry_ns = _max_gap(self._gap_carry_ns, item.gap_ns)

        # 1. decode
        try:
            rgb = M.image_to_rgb(msg)
        except M.UnsupportedEncoding as exc:
            self._drop(UNSUPPORTED_ENCODING)
            self.faults.report(UNSUPPORTED_ENCODING, f'dropping image at {stamp_ns / NS:.3f} s: {exc}')
            return
        except M.BadImage as exc:
            self._drop(BAD_IMAGE)
            self.faults.report(BAD_IMAGE, f'dropping image at {stamp_ns / NS:.3f} s: {exc}')
            return

        # 2. stream continuity: time and size
        if self._last_stamp_ns is not None:
            if stamp_ns < self._last_stamp_ns:
                epoch = self.pose_buffer.epoch
                self.faults.report(TIME_BACKWARDS, f'time went backwards: image stamp {stamp_ns / NS:.3f} s after '
                                   f'{self._last_stamp_ns / NS:.3f} s; resetting the estimator and the pose buffer '
                                   '(bag restarted or simulator reset?)', key='time_backwards:image')
                if epoch == self._last_epoch:   # odometry has not jumped back (yet): its samples are stale
                    self.pose_buffer.clear('image time went backwards')
                self._reset_estimator(f'time went backwards ({stamp_ns / NS:.3f} s after '
                                      f'{self._last_stamp_ns / NS:.3f} s)')
                self._last_size = None
            elif stamp_ns == self._last_stamp_ns:
                self._drop(DUPLICATE_STAMP)
                self.faults.report(DUPLICATE_STAMP, f'dropping image at {stamp_ns / NS:.3f} s: same stamp as the '
                                   'previous image')
                return
        self._last_stamp_ns = stamp_ns
        self._last_epoch = self.pose_buffer.epoch
        size = (rgb.shape[1], rgb.shape[0])
        if self._last_size is not None and size != self._last_size:
            change = f'{self._last_size[0]}x{self._last_size[1]}->{size[0]}x{size[1]}'
            self.faults.report(SIZE_CHANGE, f'image size changed from {self._last_size[0]}x{self._last_size[1]} '
                               f'to {size[0]}x{size[1]}; resetting the estimator', key=f'{SIZE_CHANGE}:{change}')
            self._reset_estimator(f'image size changed from {self._last_size[0]}x{self._last_size[1]} to '
                                  f'{size[0]}x{size[1]}')
        self._last_size = size

        # 3. intrinsics and pose
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
                                   f"its stamp within odom_wait_timeout {cfg['odom_wait_timeout']:g} s ({why.detail})")
            else:
                kind, label = {'gap': (ODOM_GAP, 'odometry gap'), 'too old': (ODOM_TOO_OLD, 'odometry too old'),
                               'nan': (ODOM_INVALID, 'invalid odometry around the image')}[why.reason]
                self._drop(kind)
                self.faults.report(kind, f'dropping image at {stamp_ns / NS:.3f} s ({label}): {why.detail}')
            return
        if info_size != (0, 0) and info_size != size:
            self.faults.report(CAMERA_INFO_MISMATCH, f'camera_info is for {info_size[0]}x{info_size[1]} but the image '
                               f'is {size[0]}x{size[1]}; scaling K to the image size')
            K = M.scale_K(K, info_size, size)
        T_world_cam = pose
        if pose is not None and self.pose_buffer.jumps != self._last_jumps:
            # the pose comes from after an odometry teleport: the belief is in the old frame
            self._last_jumps = self.pose_buffer.jumps
            self._reset_estimator('odometry jumped')
        if self.visual_odometry is not None:
            vo = self.visual_odometry.track(rgb, K, stamp_ns / NS)
            if not vo.tracking_ok:
                self._drop(VO_LOST)
                self.faults.report(VO_LOST, f'visual odometry lost at {stamp_ns / NS:.3f} s: {vo.reason}; '
                                   'resetting the estimator')
                self._reset_estimator(f'visual odometry lost: {vo.reason}')
                return
            T_world_cam = vo.T_world_cam_44

        # 4. estimate
        from dpv_sensor.frame import Frame
        stamp_s = stamp_ns / NS
        meta = _FrameMeta(stamp_ns, frame_id, rgb, K, size[0], size[1], item.receipt_mono, item.receipt_ns)
        gap_ns, self._gap_carry_ns = self._gap_carry_ns, None
        frame = Frame(stamp=stamp_s, image=rgb, K_33=K, T_world_cam_44=T_world_cam, frame_id=frame_id,
                      sensor_gap_s=None if gap_ns is None else gap_ns / NS)
        t0 = time.perf_counter()
        with self._estimator_lock:
            keyframes_before = self._status_int('keyframes')
            try:
                out = self.estimator.push(frame)
            except Exception as exc:
                out = None
                self._on_estimator_exception(exc)
            is_keyframe = self._status_int('keyframes') > keyframes_before
        self._last_push_ms = (time.perf_counter() - t0) * 1000.0
        self.process_ms.append(self._last_push_ms)
        if is_keyframe:
            self.keyframe_ms.append(self._last_push_ms)
        self.n_processed += 1
        self._remember(stamp_s, meta, is_keyframe)
        if out is None:
            return

        # 5. publish
        try:
            self._publish(out, current=(stamp_s, rgb))
        except Exception as exc:
            self.faults.report(PUBLISH_ERROR, f'could not publish the output for {out.stamp:.3f} s: '
                               f'{type(exc).__name__}: {exc}', level='error')

    def _status_int(self, key: str) -> int:
        if self.estimator is None:
            return 0
        try:
            return int(self.estimator.status.get(key, 0))
        except Exception:
            return 0

    def _on_estimator_exception(self, exc: Exception) -> None:
        first = self.faults.counts[ESTIMATOR_EXCEPTION] == 0
        text = f'exception inside the estimator ({type(exc).__name__}: {exc}); resetting it and going on'
        if first:
            text += '\n' + traceback.format_exc()
        self.faults.report(ESTIMATOR_EXCEPTION, text, level='error')
        self._reset_estimator(f'exception: {type(exc).__name__}: {exc}')

    def _remember(self, stamp_s: float, meta: _FrameMeta, is_keyframe: bool) -> None:
        """Keep the headers (and, for keyframes, the images) of recent frames: a centered window publishes a
        keyframe's output two keyframes later and it must carry that frame's exact header."""
        window = int(getattr(getattr(self.estimator, 'config', None), 'window_size', 5))
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
        np, M = self._np, self._M
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
        self.pub_depth.publish(M.depth_to_image(depth, header, encoding=cfg['depth_encoding']))
        self.pub_conf.publish(M.confidence_to_image(conf, header))
        self.pub_depth_info.publish(M.K_to_camera_info(K_out, w, h, header))
        if self.pub_points.get_subscription_count() > 0 and rgb_src is not None:
            rgb = rgb_src
            if rgb.shape[:2] != (h, w):
                import cv2
                rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)
            self.pub_points.publish(M.depth_to_pointcloud(depth, rgb, K_out, header))
            self.n_points += 1
        if self.pub_pose is not None and out.T_world_cam_44 is not None:
            self.pub_pose.publish(M.matrix_to_pose_stamped(out.T_world_cam_44, M.make_header(meta.stamp_ns,
                                                                                             self._odom_frame)))
            if self.tf is not None:
                self.tf.publish_refined(out.T_world_cam_44, meta.stamp_ns, self._odom_frame, meta.frame_id)
        if self.visual_odometry is not None and out.is_keyframe and rgb_src is not None:
            K_depth = None if (h, w) == rgb_src.shape[:2] else K_out
            self.visual_odometry.set_keyframe(rgb_src, meta.K_in, out.T_world_cam_44, out.depth_hw,
                                              out.confidence_hw, K_depth_33=K_depth, stamp=float(out.stamp))
        now_ns = time.time_ns()
        self.n_published += 1
        self.n_keyframes_published += int(bool(out.is_keyframe))
        self.out_rate.tick()
        self.latency_ms.append((time.monotonic() - meta.receipt_mono) * 1000.0)
        self.age_ms.append((now_ns - meta.stamp_ns) / 1e6)

    def _output_K(self, out, meta: _FrameMeta, out_wh) -> 'np.ndarray':
        """K of the output image: the input K scaled (in float64) from the input size to the output size. The
        estimator's own K_33 (computed in float32 on its device) must agree; if it does not, it is used as is."""
        np, M = self._np, self._M
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
        np = self._np
        with self._stats_lock:
            dropped = dict(self.dropped)
        try:
            st = dict(self.estimator.status) if self.estimator is not None else \
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
            'stamp_age_ms_median': round(float(np.median(age)), 1) if age else 'n/a',
            'processing_ms_median': round(float(np.median(proc)), 1) if proc else 'n/a',
            'keyframe_ms_median': round(float(np.median(kf)), 1) if kf else 'n/a',
            'dropped_total': sum(dropped.values()),
        }
        for reason, n in sorted(dropped.items()):
            values[f'dropped.{reason}'] = n
        for kind, n in sorted(self.faults.counts.items()):
            values[f'faults.{kind}'] = n
        values['filter_resets'] = st.get('resets', self._node_resets)
        values['last_reset_reason'] = st.get('last_reset_reason') or ''
        values['measurement_model'] = st.get('measurement', 'unknown')
        values['measurement_reason'] = st.get('measurement_reason', '')
        values['device'] = st.get('device', self.config['device'])
        values['precision'] = st.get('precision', '')
        values['filter_mode'] = st.get('filter_mode', self.config['filter_mode'])
        values['tracking'] = st.get('tracking', '')
        values['estimator_keyframes'] = st.get('keyframes', '')
        values['estimator_outputs'] = st.get('outputs', '')
        values['estimator_dropped'] = st.get('frames_dropped', '')
        values['estimator_last_drop_reason'] = st.get('last_drop_reason') or ''
        notes = st.get('notes') or []
        if notes:
            values['estimator_notes'] = ' | '.join(notes)
        if self.pose_refiner is not None:
            last = getattr(self.pose_refiner, 'last_result', None)
            values['pose_refinement_tracking'] = 'ok' if last is None or last.tracking_ok else f'lost: {last.reason}'
        values['pose_buffer_size'] = len(self.pose_buffer)
        values['tf'] = self.tf.status() if self.tf is not None else 'off'
        # matched publishers of the inputs, as this node's subscriptions see them (0: nothing arrives)
        values['publishers.image'] = self.sub_image.get_publisher_count()
        if self.sub_info is not None:
            values['publishers.camera_info'] = self.sub_info.get_publisher_count()
        if self.sub_odom is not None:
            values['publishers.odom'] = self.sub_odom.get_publisher_count()
        return values

    def _publish_diagnostics(self) -> None:
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
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
        total_faults = sum(n for k, n in self.faults.counts.items())
        if total_faults > self._last_fault_total:
            level = max(level, DiagnosticStatus.WARN)
            problems.append('input faults (see faults.*)')
        self._last_fault_total = total_faults
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


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv if argv is None else argv
    parser = argparse.ArgumentParser(
        prog='node', description='dpv_sensor: virtual RGB-D camera from monocular RGB + odometry. '
        'ROS arguments go after --ros-args, e.g. --ros-args --params-file config/dpv_sensor.yaml')
    parser.add_argument('--check', action='store_true', help='import all dependencies, validate defaults, exit')
    import rclpy.utilities
    own_args = rclpy.utilities.remove_ros_args(argv)[1:]
    args = parser.parse_args(own_args)
    if args.check:
        return self_check()

    # before any thread exists (DDS, the worker, OpenMP): they then share two malloc arenas (see process_memory)
    from dpv_sensor.process_memory import limit_malloc_arenas
    arenas_note = limit_malloc_arenas()

    import signal as signal_module

    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    # Import the heavy estimator stack (torch, OpenCV) before the node joins the graph, so that a node visible
    # in the graph is ready within moments.
    import dpv_sensor.estimator  # noqa: F401

    # SIGINT / SIGTERM only set a flag: a signal that arrives while the node is being built lets it finish
    # building (and log 'ready') and then stop cleanly; the spin loop below checks the flag every 0.1 s.
    stop = threading.Event()

    def on_signal(_signum, _frame):
        stop.set()

    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    previous = {sig: signal_module.signal(sig, on_signal) for sig in (signal_module.SIGINT, signal_module.SIGTERM)}
    node = None
    executor = None
    try:
        node = DepthCameraNode()
        node.get_logger().info(arenas_note)
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        while not stop.is_set() and rclpy.ok():
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except P.ParameterError as exc:
        print(f'[{NODE_NAME}] invalid parameter: {exc}', file=sys.stderr)
        return 2
    except StartupError as exc:
        print(f'[{NODE_NAME}] {exc}', file=sys.stderr)
        return 2
    finally:
        if executor is not None:
            executor.shutdown()
        if node is not None:
            node.close()
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
        for sig, handler in previous.items():
            signal_module.signal(sig, handler)
    if node is not None and node.fatal_error:
        print(f'[{NODE_NAME}] {node.fatal_error}', file=sys.stderr)
        return 2
    return 0


if __name__ == '__main__':
    sys.exit(main())
