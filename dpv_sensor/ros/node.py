"""`ros2 run dpv_sensor node`: the rclpy adapter of the virtual depth camera, a thin one.

The node composes its parts, each its own module: the typed settings (``node_params``), the inputs (``inputs``:
subscriptions, QoS, what the callbacks store), the worker thread that runs the pipeline (``worker``), the outputs
(``outputs``: publishers, headers, output counters) and /diagnostics (``diagnostics``). The algorithm lives in the
stream layer (``dpv_sensor.stream.pipeline.Pipeline.push(Frame) -> PushResult``, the continuity rules in
``dpv_sensor.stream.continuity``); messages are converted by ``dpv_sensor.ros.msgs``.

Topics (relative names, remappable; a camera_info or compressedDepth follows its remapped image topic as
image_transport names them, as does image/compressed, unless remapped itself: dpv_sensor.ros.topic_names):
  in   image (sensor_msgs/Image rgb8/bgr8/rgba8/bgra8/mono8; with image_transport compressed instead
       image/compressed: sensor_msgs/CompressedImage JPEG/PNG as image_transport's compressed plugin publishes it,
       decoded on receipt, dpv_sensor.ros.compressed_image), camera_info (sensor_msgs/CameraInfo),
       odom (nav_msgs/Odometry) - QoS: input_reliability (auto: as the publishers offer), input_depth; transport:
       dpv_sensor.ros.transport (docs/transport.md), applied by the start-up steps before rclpy starts
       /tf_static, /tf (tf2_msgs/TFMessage), with extrinsic_source tf: the camera mount from the odometry's child
       frame to the image frame (dpv_sensor.ros.extrinsic)
  out  depth/image (32FC1 m, NaN = none | 16UC1 mm, 0 = none), depth/camera_info (K of the output size),
       rgb/image (rgb8: the colour image the depth was computed for, rectified when the node rectifies, at the
       depth's size) + rgb/camera_info, confidence/image (32FC1 in [0, 1]) + confidence/camera_info (all camera_info
       the same: K of the output size, D zero), depth/image/compressedDepth (with publish_compressed_depth),
       depth/points (PointCloud2 XYZRGB, only computed while subscribed; points_decimation, points_max_rate),
       pose (PoseStamped, with pose_refinement or odometry none), /diagnostics (DiagnosticArray)
       with publish_tf: /tf_static (base_frame -> image frame, T_base_camera; not when the mount comes from TF)
       and /tf (<image frame>_refined,
       with the pose output), tf2_msgs/TFMessage (dpv_sensor.ros.tf_publisher)

Threading: callbacks only store messages. The newest image waits in a one-slot mailbox ("newest wins": an image
that is still waiting when a newer one arrives is dropped and counted) and the worker thread converts it, waits up to
odom_wait_timeout for odometry after its stamp, runs the pipeline and publishes. Memory stays flat whatever the
input rate. Every output carries exactly the input image's header (stamp and frame_id). The worker builds the
pipeline when the node starts ('starting' is logged once topics and parameters are up, 'ready' once the model is
loaded); if it cannot be built (e.g. measurement=network without weights) the node logs that one error and exits
with code 2. SIGINT / SIGTERM stop the node cleanly (exit 0), also while it is still starting: the start-up steps
(dpv_sensor.ros.startup) install the handlers before this module's heavy imports.

Distorted input (camera_info with non-zero D, plumb_bob / rational_polynomial / equidistant) is rectified
(dpv_sensor.core.rectify) before the estimator; every output then carries the rectified K with D zero.

Bad input never stops the node: each kind of fault (``fault_kinds``: unsupported encoding, inconsistent image, a
compressed image that cannot be decoded, an image too small for the estimator, a stray image of another size (a new
size is taken once it persists: size_change_images), size change, missing or zero camera_info, NaN odometry or NaN
in its covariance, odometry stamped 0, odometry gap or timeout, conflicting odometry at one stamp, time going
backwards, an empty image frame_id, no camera mount on TF yet, a second camera (another frame_id) on the image
topic, a degenerate image, an exception inside the estimator) is counted, reported in /diagnostics and logged with a
specific, rate-limited message. No image is lost uncounted: images lost before the callback (transport) are counted
from the publisher's sequence numbers (the image callback takes the message info), the middleware's reports and the
stamps (lost.*), images the node skips or refuses in dropped.* (an image replaced in the mailbox while the worker
waited for odometry that then came too late: odometry_late; for the camera mount: no_extrinsic; else busy; an image
stamped ahead of the clock and the odometry: future_stamp). A loss is counted only on evidence (a sequence gap, a
middleware report, or a stamp gap the stream around it confirms): a camera that lowers its rate loses nothing
(input_rate_changes) and a stamp jump is a discontinuity (input_stamp_jumps, faults.stamp_jump).
"""
from __future__ import annotations

if __name__ == '__main__':     # python -m dpv_sensor.ros.node: signal handlers before the heavy imports below
    from dpv_sensor.ros.startup import prepare as _prepare
    _prepare()

import collections
import sys
import threading

import rclpy
from rclpy.clock import Clock, ClockType
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from dpv_sensor import params as P
from dpv_sensor.ros import startup
from dpv_sensor.ros.diagnostics import NodeDiagnostics
from dpv_sensor.ros.extrinsic import pose_text
from dpv_sensor.ros.inputs import QOS_CHECK_PERIOD_S, NodeInputs
from dpv_sensor.ros.node_params import NodeSettings, RuntimeParameters, declare_parameters
from dpv_sensor.ros.node_support import FaultLog, LogBridge
from dpv_sensor.ros.outputs import NodeOutputs
from dpv_sensor.ros.qos import QosEvents
from dpv_sensor.ros.worker import StartupError, Worker
from dpv_sensor.stream.pose_buffer import pose7_to_matrix

NODE_NAME = 'dpv_sensor'


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


class DepthCameraNode(Node):
    """The virtual depth camera on the ROS graph: settings, inputs, worker, outputs, diagnostics."""

    def __init__(self, **kwargs):
        super().__init__(NODE_NAME, **kwargs)
        self._values = declare_parameters(self)
        self.settings = NodeSettings.from_params(self._values)
        log = self.get_logger()
        self.faults = FaultLog(log)
        self._dropped: collections.Counter = collections.Counter()
        self._stats_lock = threading.Lock()
        self._log_bridge = LogBridge(log).attach()
        T_base_camera = pose7_to_matrix(self.settings.node.T_base_camera)
        extrinsic_source = P.extrinsic_source(self.settings.node.extrinsic_source, self.settings.node.T_base_camera)
        self.qos_events = QosEvents(self.faults)
        self.inputs = NodeInputs(self, self.faults, self.qos_events, self.drop, T_base_camera, extrinsic_source)
        if self.settings.node.input_reliability == 'auto':
            # on the steady clock: under use_sim_time a ROS-time timer would wait for /clock, and the inputs would
            # never follow their publishers' QoS until it comes
            self.create_timer(QOS_CHECK_PERIOD_S, self.inputs.adapt_qos, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.outputs = NodeOutputs(self, self.faults, self.qos_events,
                                   T_base_camera if extrinsic_source == 'parameter' else None)
        self.inputs.tf = self.outputs.tf
        self.diagnostics = NodeDiagnostics(self)
        self.worker = Worker(self, self.faults, self.inputs, self.outputs, self.drop)
        self.worker.start()
        # on the steady clock: diagnostics keep coming while sim time (use_sim_time) is paused or not yet published
        self.create_timer(self.settings.node.diagnostics_period, self.diagnostics.publish,
                          clock=Clock(clock_type=ClockType.STEADY_TIME))
        self._runtime_params = RuntimeParameters(self, self._values, self._apply_parameters)
        log.info(self._starting_line())

    def _starting_line(self) -> str:
        est, s = self.settings.estimator, self.settings.node
        ratio = f' {est.confidence_ratio:g}' if est.confidence == 'ratio' else ''
        return (f'starting (building the estimator): preset={est.preset} device={est.device}'
                f' cpu_precision={est.cpu_precision} measurement={est.measurement} '
                f'filter={est.filter_mode} readout={est.depth_readout} confidence={est.confidence}{ratio} '
                f'odometry={est.odometry} processing={est.processing_width}x{est.processing_height} '
                f'input QoS={s.input_reliability}/{s.input_depth} image_transport={s.image_transport} '
                f"image='{self.inputs.topic_name('image')}' "
                f"camera_info='{self.inputs.topic_name('camera_info') or 'parameters'}' "
                f"odom='{self.inputs.topic_name('odom') or 'none'}' "
                f'camera mount={self._mount_line()}')

    def _mount_line(self) -> str:
        """Where the camera mount comes from, for the starting line."""
        ext = self.inputs.extrinsic
        if self.settings.estimator.odometry != 'topic':
            return 'unused (odometry none)'
        if ext.source == 'parameter':
            T = pose7_to_matrix(self.settings.node.T_base_camera)
            return f'{ext.description()}: T_base_camera {pose_text(T)}'
        return f'{ext.description()}: looked up on /tf_static and /tf (odometry child frame -> image frame)'

    @property
    def failed(self) -> threading.Event:
        """Set when the pipeline cannot be built (``fatal_error`` says why)."""
        return self.worker.failed

    @property
    def fatal_error(self) -> str | None:
        return self.worker.fatal_error

    def drop(self, reason: str) -> None:
        """Count an image the node skipped or refused (dropped.<reason>)."""
        with self._stats_lock:
            self._dropped[reason] += 1

    def dropped_counts(self) -> dict:
        with self._stats_lock:
            return dict(self._dropped)

    def _apply_parameters(self, values: dict, changes: dict) -> None:
        """Accepted runtime parameter changes (params.RUNTIME): the node reads its settings at use; the estimator's
        are set on the running pipeline (a pipeline built later takes them from the settings)."""
        with self.worker.lock:
            self.settings = NodeSettings.from_params(values)
            self.worker.apply_settings(changes)

    def close(self) -> bool:
        """Stop the worker and release resources before the node is destroyed; True when the worker stopped."""
        stopped = self.worker.join(timeout=10.0)
        self._log_bridge.detach()
        return stopped


def run(argv: list[str], stop: threading.Event) -> int:
    """Build the node and spin it until ``stop`` is set (SIGINT / SIGTERM, see ``dpv_sensor.ros.startup``) or the
    worker reports that the pipeline cannot be built. Returns the exit code: 0, or 2 for a refused parameter or a
    failed start (with the one message on stderr). Only this thread creates and shuts down the ROS context."""
    # set by the start-up steps before any thread existed (DDS, the worker, OpenMP; see process_memory)
    malloc_note = startup.malloc_note()
    # the node's DDS transport, before rclpy.init (applied by the start-up steps already; idempotent)
    transport_note = startup.apply_transport_settings()
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
        node.get_logger().info(malloc_note)
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
    """The node program from this module (``python -m dpv_sensor.ros.node``): ``startup.main`` with this module's
    ``run`` and ``self_check``."""
    return startup.main(argv, lambda: (run, self_check))


if __name__ == '__main__':
    startup.exit_process(main())
