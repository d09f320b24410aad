"""The node's worker thread: it builds the pipeline (loading weights / CUDA can take seconds; the node meanwhile
buffers odometry, keeps the newest image and reports 'starting'), then takes the newest image from the mailbox and
carries it to a published output in named steps: decode, the stream rules on received images
(``dpv_sensor.stream.continuity.ReceivedImages``: time order, size changes, odometry teleports), camera_info and the
odometry pose (waiting up to odom_wait_timeout), rectification, the pipeline, publishing. Each step counts and
reports its own drops; the worker survives anything (internal_error).

Dropping is deliberate and does not break the stream: every Frame carries `sensor_gap_s`, the longest interval
between consecutive images the node *received* since the previous frame it pushed (dropped images included), so the
estimator's time-gap reset fires only when the camera stream itself stalled.
"""
from __future__ import annotations

import collections
import threading
import time
import traceback

from dpv_sensor import params as P
from dpv_sensor.ros import msgs as M
from dpv_sensor.ros.fault_kinds import (CAMERA_INFO_MISMATCH, DUPLICATE_STAMP, ESTIMATOR_EXCEPTION, FUTURE_STAMP,
                                        INTERNAL_ERROR, NO_CAMERA_INFO, NO_EXTRINSIC, ODOM_GAP, ODOM_INVALID,
                                        ODOM_TIMEOUT, ODOM_TOO_OLD, RECTIFY_SIZE, SIZE_CHANGE, TIME_BACKWARDS)
from dpv_sensor.ros.inputs import FROM_THE_FUTURE, NO_MOUNT
from dpv_sensor.ros.node_support import Incoming, camera_gap_ns, max_gap
from dpv_sensor.ros.outputs import FrameMeta
from dpv_sensor.ros.receipt import BAD_IMAGE, UNSUPPORTED_ENCODING
from dpv_sensor.ros.worker_load import WorkerLoad
from dpv_sensor.stream.continuity import ReceivedImages
from dpv_sensor.stream.estimator import EstimatorConfig, EstimatorStatus
from dpv_sensor.stream.frame import Frame
from dpv_sensor.stream.pipeline import DEGENERATE, VO_LOST, Pipeline

NS = 1_000_000_000

# How long after its receipt an image waits for the middleware's report of images lost right before it (Fast DDS
# reports them when the next sample arrives, but the report and the image reach the node by separate callbacks):
# a gap the report explains is no gap in the camera stream. Only images that end a gap no report explains yet wait.
LOSS_REPORT_WAIT_S = 0.2

# why an odometry pose lookup failed (PoseQuery.reason) -> (the counter, its words)
_NO_POSE = {'gap': (ODOM_GAP, 'odometry gap'), 'too old': (ODOM_TOO_OLD, 'odometry too old'),
            'nan': (ODOM_INVALID, 'invalid odometry around the image')}


class StartupError(RuntimeError):
    """The node cannot start (e.g. the estimator cannot be built with the given parameters)."""


class Worker:
    """The pipeline and the thread that feeds it. `node`: the rclpy node (``settings``, ``get_logger``);
    `drop(reason)`: counts a dropped image (dropped.*)."""

    def __init__(self, node, faults, inputs, outputs, drop):
        self.node = node
        self.faults = faults
        self.inputs = inputs
        self.outputs = outputs
        self._drop = drop
        self.pipeline: Pipeline | None = None
        self.fatal_error: str | None = None
        self.failed = threading.Event()           # set when the pipeline cannot be built
        self.lock = threading.RLock()             # the pipeline (worker, parameter changes, diagnostics)
        self.stop = threading.Event()
        self._stream = ReceivedImages(inputs.pose_buffer)
        self._gap_carry_ns = None             # longest image gap since the last push
        self._loss_carry: list = []           # stream_loss.Gap of images lost since the last push
        # estimator timings and counters
        self.process_ms: collections.deque[float] = collections.deque(maxlen=200)   # estimator.push, any frame
        self.keyframe_ms: collections.deque[float] = collections.deque(maxlen=50)   # estimator.push, keyframes
        self.last_keyframe_ms = None
        self.load = WorkerLoad()              # busy share and the keyframes' stage medians (/diagnostics)
        self.n_processed = 0
        self.n_resets = 0                     # restarts the node asked for or saw (diagnostics without a status)
        self._degenerate_run = 0              # consecutive degenerate images
        self._degenerate_reason = ''
        self.n_degenerate_episodes = 0
        self._thread = threading.Thread(target=self._work, name='dpv_sensor_worker', daemon=True)

    def start(self) -> None:
        self._thread.start()

    def join(self, timeout: float) -> bool:
        """Stop the thread; True when it stopped within `timeout` s."""
        self.stop.set()
        self.inputs.mailbox.close()
        self.inputs.wake()
        if self._thread.is_alive():
            self._thread.join(timeout=timeout)
        return not self._thread.is_alive()

    # ------------------------------------------------------------------------------------------ the pipeline
    def status(self) -> EstimatorStatus | None:
        """The pipeline's status, None while it is being built."""
        pipeline = self.pipeline
        return None if pipeline is None else pipeline.status

    def _make_pipeline(self) -> Pipeline:
        try:
            # a config of its own: the pipeline changes its runtime settings in place
            return Pipeline(EstimatorConfig.from_params(self.node.settings.estimator.as_dict()),
                            mount_text=self._mount_text)
        except P.ParameterError as exc:     # a setting the estimator refuses once built (confidence_calibration)
            raise StartupError(f'invalid parameter: {exc}') from exc
        except Exception as exc:
            raise StartupError(f'cannot build the estimator: {type(exc).__name__}: {exc}') from exc

    def _mount_text(self, fit) -> str:
        """What to set for a mount-check fit: the T_base_camera line with the parameter's mount, else where the
        mount comes from."""
        from dpv_sensor.core.mount_calibration import corrected_mount
        from dpv_sensor.stream.pose_buffer import matrix_to_pose7, pose7_to_matrix
        node = self.node.settings.node
        if P.extrinsic_source(node.extrinsic_source, node.T_base_camera) != 'parameter':
            return ('the mount comes from TF: correct the transform there (calibrate_mount on a recording prints it '
                    'whole)')
        new = matrix_to_pose7(corrected_mount(pose7_to_matrix(node.T_base_camera), fit))
        return 'set T_base_camera:=[' + ', '.join(f'{v:.6g}' for v in new) + ']'

    def _build(self) -> bool:
        """The pipeline (pose source and estimator). On failure the node reports a fatal error: ``failed`` is set
        and the node's spin loop stops (exit code 2 with the reason). The worker never shuts the context down
        itself: the main thread owns it."""
        log = self.node.get_logger()
        try:
            pipeline = self._make_pipeline()
        except Exception as exc:
            self.fatal_error = str(exc) if isinstance(exc, StartupError) else \
                f'cannot start: {type(exc).__name__}: {exc}'
            log.error(self.fatal_error)
            self.failed.set()
            return False
        with self.lock:
            self.pipeline = pipeline
        st = pipeline.status
        log.info(f'ready: measurement={st.measurement} ({st.measurement_reason}) device={st.device} '
                 f'filter={st.filter_mode} window={st.window_mode} planes={st.num_planes} '
                 f'depth range={st.depth_range}')
        return True

    def apply_settings(self, changes: dict) -> None:
        """Runtime changes of the estimator's settings, on the running pipeline."""
        with self.lock:
            if self.pipeline is not None:
                self.pipeline.apply_settings(changes)

    def _reset(self, reason: str) -> None:
        self.n_resets += 1
        with self.lock:
            try:
                self.pipeline.reset(reason)
            except Exception as exc:
                self.node.get_logger().error(f'pipeline reset failed ({type(exc).__name__}: {exc}); rebuilding it')
                self.pipeline = self._make_pipeline()
        self._forget()

    def _forget(self) -> None:
        """The node's own stream state after a restart: the carried image gap and the recent frame headers."""
        self._gap_carry_ns = None
        self._loss_carry = []
        self.outputs.forget()

    # ------------------------------------------------------------------------------------------ the loop
    def _work(self) -> None:
        if not self._build():
            return
        while not self.stop.is_set():
            item = self.inputs.mailbox.take(timeout=0.2)
            if item is None:
                continue
            start = time.monotonic()
            try:
                self._process(item)
            except Exception as exc:   # the worker must survive anything
                self.faults.report(INTERNAL_ERROR, f'unexpected error while processing an image: '
                                   f'{type(exc).__name__}: {exc}\n{traceback.format_exc()}', level='error')
            finally:
                self.load.busy(start, time.monotonic())

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
            self.outputs.publish_output(out, rgb, stamp_ns, self.inputs.odom_frame)

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
        """The stream rules on the received images (``ReceivedImages``), before the pose lookup: a stream that went
        backwards restarts the odometry buffer too. False: drop the image (a duplicate stamp)."""
        verdict = self._stream.image(stamp_ns, size)
        if verdict.duplicate:
            self._drop(DUPLICATE_STAMP)
            self.faults.report(DUPLICATE_STAMP, f'dropping image at {stamp_ns / NS:.3f} s: same stamp as the '
                               'previous image')
            return False
        if verdict.backwards is not None:
            self.faults.report(TIME_BACKWARDS, f'time went backwards: image stamp {stamp_ns / NS:.3f} s after '
                               f'{verdict.previous_ns / NS:.3f} s; resetting the estimator and the pose buffer '
                               '(bag restarted or simulator reset?)', key='time_backwards:image')
            self._reset(verdict.backwards)
        if verdict.size_change is not None:
            (w0, h0), (w, h) = verdict.previous_size, size
            self.faults.report(SIZE_CHANGE, f'{verdict.size_change}; resetting the estimator',
                               key=f'{SIZE_CHANGE}:{w0}x{h0}->{w}x{h}')
            self._reset(verdict.size_change)
        return True

    def _camera_and_pose(self, item: Incoming, stamp_ns: int, size):
        """(K of the image size, odometry pose or None without odometry), or None when the image must be dropped
        (no camera_info yet, no odometry in time, an odometry gap ...). Resets on an odometry teleport."""
        K, info_size, pose, why = self.inputs.wait_for(item, stamp_ns, self.stop)
        if K is None:
            if why is not None and why.reason == NO_MOUNT:
                self._no_mount(item, stamp_ns, why.detail)
                return None
            self._no_inputs(stamp_ns, why)
            return None
        if info_size != (0, 0) and info_size != size:
            self.faults.report(CAMERA_INFO_MISMATCH, f'camera_info is for {info_size[0]}x{info_size[1]} but the image '
                               f'is {size[0]}x{size[1]}; scaling K to the image size')
            K = M.scale_K(K, info_size, size)
        if pose is not None and self._stream.pose_teleported():
            self._reset('odometry jumped')      # the pose comes from after an odometry teleport
        return K, pose

    def _no_mount(self, item: Incoming, stamp_ns: int, detail: str) -> None:
        """Count and report an image dropped for want of the camera mount on TF (extrinsic_source tf)."""
        base, image = self.inputs.image_frames(item)
        self._drop(NO_EXTRINSIC)
        self.faults.report(NO_EXTRINSIC, f"dropping image at {stamp_ns / NS:.3f} s: no transform from '{base}' to "
                           f"'{image}' on /tf_static or /tf yet ({detail}); set T_base_camera or publish the camera "
                           'mount (robot_state_publisher)', key=f'{NO_EXTRINSIC}:{base}->{image}')

    def _no_inputs(self, stamp_ns: int, why) -> None:
        """Count and report an image dropped for want of camera_info (`why` None) or of an odometry pose."""
        if why is None:
            self._drop(NO_CAMERA_INFO)
            where = self.inputs.topic_name('camera_info') or 'parameters'
            self.faults.report(NO_CAMERA_INFO, f'no camera_info received yet on {where}; waiting '
                               '(images are dropped until it arrives)')
        elif why.reason == FROM_THE_FUTURE:
            self._drop(FUTURE_STAMP)
            self.faults.report(FUTURE_STAMP, f'dropping image at {stamp_ns / NS:.3f} s: {why.detail} (more than '
                               f'future_stamp_tolerance {self.node.settings.node.future_stamp_tolerance:g} s): no '
                               "odometry can come for it by waiting: the camera's clock runs ahead of the node's and "
                               "the odometry's (synchronise the clocks, e.g. with chrony) or the driver stamps its "
                               'images wrongly (dropped.future_stamp counts them)', period_s=30.0)
        elif why.reason == 'future':
            self._drop(ODOM_TIMEOUT)
            self.faults.report(ODOM_TIMEOUT, f'dropping image at {stamp_ns / NS:.3f} s: no odometry at or after '
                               f'its stamp within odom_wait_timeout {self.node.settings.node.odom_wait_timeout:g} s '
                               f'({why.detail})')
        else:
            kind, label = _NO_POSE[why.reason]
            self._drop(kind)
            self.faults.report(kind, f'dropping image at {stamp_ns / NS:.3f} s ({label}): {why.detail}')

    def _rectify(self, rgb, stamp_ns: int):
        """The image undistorted with the current camera_info's maps (as it is without distortion)."""
        rect = self.inputs.rectifier
        if rect is None:
            return rgb
        if (rgb.shape[1], rgb.shape[0]) != rect.size:
            self.faults.report(RECTIFY_SIZE, f'image at {stamp_ns / NS:.3f} s is {rgb.shape[1]}x{rgb.shape[0]} but '
                               f'the distorted camera_info is for {rect.size[0]}x{rect.size[1]}; used as it is')
            return rgb
        return rect.rectify(rgb)

    def _estimate(self, item: Incoming, stamp_ns: int, rgb, K, pose):
        """Push the frame through the pipeline; the output that became ready, or None."""
        frame_id = item.msg.header.frame_id or self.node.settings.node.frame_id
        stamp_s = stamp_ns / NS
        meta = FrameMeta(stamp_ns, frame_id, rgb, K, rgb.shape[1], rgb.shape[0], item.receipt_mono, item.receipt_ns)
        gap_ns = self._stream_gap_ns(item)
        frame = Frame(stamp=stamp_s, image=rgb, K_33=K, T_world_cam_44=pose, frame_id=frame_id,
                      sensor_gap_s=None if gap_ns is None else gap_ns / NS,
                      pose_covariance_66=self.inputs.covariances.pose.at(stamp_ns) if pose is not None else None,
                      twist_covariance_66=self.inputs.covariances.twist.at(stamp_ns) if pose is not None else None)
        t0 = time.perf_counter()
        with self.lock:
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
            # the pipeline restarted itself; the node forgets its own stream state
            self._drop(VO_LOST)
            self.faults.report(VO_LOST, f'visual odometry lost at {stamp_s:.3f} s: {result.detail}; '
                               'resetting the estimator')
            self.n_resets += 1
            self._forget()
            return None
        is_keyframe = result is not None and result.is_keyframe
        push_ms = (time.perf_counter() - t0) * 1000.0
        self.process_ms.append(push_ms)
        if is_keyframe:
            self.keyframe_ms.append(push_ms)
            self.last_keyframe_ms = push_ms
        if result is not None and result.output is not None and result.output.is_keyframe:
            self.load.keyframe(result.output.timings_ms)
        self.n_processed += 1
        self.outputs.remember(stamp_s, meta, is_keyframe, self.pipeline.config.window_size)
        return None if result is None else result.output

    def _stream_gap_ns(self, item: Incoming) -> int | None:
        """The camera stream's longest gap since the last push (Frame.sensor_gap_s), taking the carry: intervals with
        images lost in transport count as one period when the middleware reported them lost, for which an image
        waits up to LOSS_REPORT_WAIT_S after its receipt."""
        pending, self._loss_carry = self._loss_carry, []
        deadline = item.receipt_mono + LOSS_REPORT_WAIT_S
        while any(not g.settled for g in pending) and time.monotonic() < deadline and not self.stop.is_set():
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

    def _on_estimator_exception(self, exc: Exception) -> None:
        first = self.faults.counts[ESTIMATOR_EXCEPTION] == 0
        text = f'exception inside the estimator ({type(exc).__name__}: {exc}); resetting it and going on'
        if first:
            text += '\n' + traceback.format_exc()
        self.faults.report(ESTIMATOR_EXCEPTION, text, level='error')
        self._reset(f'exception: {type(exc).__name__}: {exc}')
