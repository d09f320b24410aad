"""The node's /diagnostics: one DiagnosticStatus per diagnostics_period (on the steady clock: it keeps coming while
sim time is paused) with every counter as a key/value, and its level and message: per output a measured rate
against expected_depth_rate / expected_points_rate, the share of recent images lost in transport (lost.transport) or
rejected as faulty (dropped.* other than busy) against drop_warn_share / drop_error_share, new input faults,
estimator exceptions, the classical fallback, a stalled input, a TF fault holding the camera mount (while it lasts).
Counters: frames_received + lost.transport = images sent and frames_processed + dropped_total = frames_received (but
for the one or two in flight)."""
from __future__ import annotations

import collections
import math
import pathlib
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from dpv_sensor.ros.fault_kinds import BUSY, ESTIMATOR_EXCEPTION
from dpv_sensor.stream.estimator import EstimatorStatus


# a share of lost or rejected images is over once this many images in a row arrived clean
CLEAN_IMAGES_OVER = 10


def _median(values, digits: int = 1):
    return round(float(np.median(values)), digits) if values else 'n/a'


def pose_uncertainty_text(last: dict | None, setting: str) -> str:
    """The /diagnostics value of the last keyframe's pose uncertainty: its source and size, or the setting."""
    if setting == 'off' or not last:
        return setting if setting == 'off' else f'{setting} (no keyframe yet)'
    if 'rot_deg_max' not in last:
        return str(last.get('source'))
    return (f"{last['source']}: rotation {last['rot_deg_max']:.3f} deg, translation {last['trans_mm_max']:.2f} mm "
            f"(largest source, per axis), median {last['median_planes']:.2f} planes")


def calibration_text(path: str | None) -> str:
    """The confidence calibration in use, as /diagnostics shows it: the file's name, or 'off'."""
    return pathlib.PurePath(path).name if path else 'off'


def _share(value) -> str | float:
    return 'n/a' if value is None else round(float(value), 3)


def estimator_values(st: EstimatorStatus | None, settings, starting: bool, resets: int) -> dict:
    """The estimator's part of /diagnostics from its status; without one (`starting`: the pipeline is being built,
    else its status failed) the settings' values."""
    est = settings.estimator
    if st is None:
        return {'filter_resets': resets, 'last_reset_reason': '',
                'measurement_model': 'starting' if starting else 'unknown', 'measurement_reason': '',
                'device': est.device, 'precision': '', 'filter_mode': est.filter_mode,
                'tracking': 'building the estimator' if starting else '',
                'pose_uncertainty': pose_uncertainty_text(None, est.pose_uncertainty),
                'estimator_keyframes': '', 'estimator_outputs': '', 'estimator_dropped': '',
                'estimator_last_drop_reason': '',
                'confidence_calibration': calibration_text(est.confidence_calibration or None)}
    values = {'filter_resets': st.resets, 'last_reset_reason': st.last_reset_reason or '',
              'measurement_model': st.measurement, 'measurement_reason': st.measurement_reason,
              'device': st.device, 'precision': st.precision, 'filter_mode': st.filter_mode, 'tracking': st.tracking,
              'pose_uncertainty': pose_uncertainty_text(st.pose_uncertainty, est.pose_uncertainty),
              'estimator_keyframes': st.keyframes, 'estimator_outputs': st.outputs,
              'estimator_dropped': st.frames_dropped, 'estimator_last_drop_reason': st.last_drop_reason or '',
              'confidence_calibration': calibration_text(st.confidence_calibration)}
    if st.notes:
        values['estimator_notes'] = ' | '.join(st.notes)
    if st.pose_refinement_tracking is not None:
        values['pose_refinement_tracking'] = st.pose_refinement_tracking
        values['pose_refinement_fallbacks'] = st.pose_refinement_fallbacks
        values['pose_refinement_last_fallback'] = st.last_pose_refinement_fallback_reason or ''
    if st.pose_refinement_gate:
        values['pose_refinement_gate'] = ', '.join(f'{k} {v}' for k, v in sorted(st.pose_refinement_gate.items()))
    if st.pose_refinement_factors:
        values['pose_refinement_factors'] = ', '.join(f'{k} {v}'
                                                      for k, v in sorted(st.pose_refinement_factors.items()))
        values['pose_refinement_correction'] = (f'{1000 * st.pose_refinement_correction[0]:.1f} mm / '
                                                f'{st.pose_refinement_correction[1]:.3f} deg')
    if st.pose_refinement_direction_ratio is not None:
        median, limit = st.pose_refinement_direction_ratio
        values['pose_refinement_direction_ratio'] = (
            f'{median:.3f} (images {"agree" if median <= limit else "disagree"} with the odometry\'s directions; '
            f'flow rotations at most {limit:g})')
    if st.anchors:
        values.update(anchor_values(st.anchors))
    if st.mount_check:
        values.update(mount_values(st.mount_check))
    if st.pose_refinement_odometry is not None:
        rot, trans, source = st.pose_refinement_odometry
        values['pose_refinement_odometry'] = (f'{math.degrees(rot):.3f} deg / {1000 * trans:.2f} mm per keyframe '
                                              f'step ({source})')
    return values


def _triple(v, fmt: str) -> str:
    return '[' + ', '.join('n/a' if x is None else format(x, fmt) for x in v) + ']'


def mount_values(mount: dict) -> dict:
    """The mount check's part of /diagnostics (``EstimatorStatus.mount_check``): ``mount_estimate`` (the rotation
    and translation of the camera from the mount in use, with sigmas, 'OFF' when confidently away from it) and
    ``time_offset_estimate`` (ms, + = the odometry is stamped late), or why there is none yet."""
    fit = mount.get('fit')
    pairs = mount.get('pairs', 0)
    if fit is None:
        waiting = f'no estimate yet ({pairs} image pairs measured)'
        return {'mount_estimate': waiting, 'time_offset_estimate': waiting}
    if not fit.get('ok'):
        why = f"no estimate: {fit.get('reason')}"
        return {'mount_estimate': why, 'time_offset_estimate': why}
    verdict = 'OFF' if mount.get('rotation_off') or mount.get('translation_off') else 'ok'
    shift = (f", shift {_triple(fit['translation_mm'], '+.0f')} +- {_triple(fit['sigma_trans_mm'], '.0f')} mm"
             if all(v is not None for v in fit['sigma_trans_mm']) else ', shift not observed')
    mount_text = (f"{verdict}: {fit['angle_deg']:.2f} deg, rotation vector {_triple(fit['rotvec_deg'], '+.2f')} +- "
                  f"{_triple(fit['sigma_rot_deg'], '.2f')} deg (camera x, y, z){shift}; {fit['pairs']} pairs")
    if fit.get('sigma_time_ms') is None:
        offset_text = 'not fitted'
    else:
        offset_text = (f"{'OFF' if mount.get('offset_off') else 'ok'}: {fit['time_offset_ms']:+.1f} +- "
                       f"{fit['sigma_time_ms']:.1f} ms (+: the odometry is stamped late)")
    return {'mount_estimate': mount_text, 'time_offset_estimate': offset_text}


def anchor_values(anchors: dict) -> dict:
    """The metric anchors' part of /diagnostics (``EstimatorStatus.anchors``): the mode, keyframes checked, aligned
    and overruled (a region disagreed with its anchors beyond their sigma) and those where the classical sweep was
    blended into the overruled region (``anchor_fallback``), anchors per checked keyframe, rejected
    candidates by reason, and the last keyframe's anchors, scale and why nothing was applied."""
    checked = anchors.get('keyframes_checked', 0)
    values = {'depth_anchors': anchors.get('mode', 'off'),
              'anchors_keyframes': (f"{checked} checked, {anchors.get('keyframes_aligned', 0)} aligned, "
                                    f"{anchors.get('keyframes_overruled', 0)} overruled "
                                    f"({anchors.get('pixels_overruled', 0)} pixels), "
                                    f"{anchors.get('keyframes_fallback', 0)} with the classical sweep blended in "
                                    f"({anchors.get('pixels_fallback', 0)} pixels mostly the sweep's)"),
              'anchors_per_keyframe': f"{anchors.get('anchors', 0) / checked:.0f}" if checked else '0',
              'anchors_rejected': ', '.join(f'{k} {v}' for k, v in sorted((anchors.get('rejected') or {}).items()))}
    last = anchors.get('last') or {}
    scale = last.get('scale')
    values['anchors_last'] = (f"{last.get('anchors', 0)} anchors, {last.get('used', 0)} on the depth, "
                              + (f"scale {scale:.3f} +- {100 * last.get('sigma', 0.0):.1f} %, applied "
                                 f"{last.get('applied', 'none')}" if scale is not None else 'no fit')
                              + (f" ({last['reason']})" if last.get('reason') else ''))
    return values


class NodeDiagnostics:
    """Builds and publishes /diagnostics from the node's parts (inputs, outputs, worker, faults, drops)."""

    def __init__(self, node):
        self.node = node
        self.pub = node.create_publisher(DiagnosticArray, '/diagnostics', 10)
        # (mono, received, faulty, lost) at each diagnostics tick, from the start (nothing received yet)
        self._share_history: collections.deque = collections.deque([(time.monotonic(), 0, 0.0, 0.0)])
        self._last_fault_total = 0
        self._last_exception_count = 0
        self._bad_total = 0.0              # images lost or rejected as faulty, all told, at the latest growth
        self._received_at_bad = 0          # images received when that count last grew

    def _sim_time(self) -> bool:
        try:
            return bool(self.node.get_parameter('use_sim_time').value)
        except Exception:   # not declared (a node without the parameter)
            return False

    def _estimator(self) -> dict:
        worker = self.node.worker
        try:
            st = worker.status()
        except Exception:
            return estimator_values(None, self.node.settings, False, worker.n_resets)
        return estimator_values(st, self.node.settings, st is None, worker.n_resets)

    def values(self) -> dict:
        """Everything /diagnostics reports, as a flat {key: value} dict."""
        node, inputs, outputs, worker = self.node, self.node.inputs, self.node.outputs, self.node.worker
        s = node.settings.node
        dropped = node.dropped_counts()
        est = self._estimator()
        lat, age = list(outputs.latency_ms), list(outputs.age_ms)
        first_image = inputs.first_image_mono
        values = {
            'input_rate_hz': round(inputs.in_rate.rate(), 3),
            'output_rate_hz': round(outputs.rate.rate(), 3),
            'frames_received': inputs.n_received,
            'odometry_received': inputs.n_odometry_received,
            'frames_processed': worker.n_processed,
            'outputs_published': outputs.n_published,
            'keyframes_published': outputs.n_keyframes_published,
            'point_clouds_published': outputs.n_points,
            'latency_ms_median': _median(lat),
            'latency_ms_p95': round(float(np.percentile(lat, 95)), 1) if lat else 'n/a',
            # on the node's clock (ROS time under use_sim_time), for stamps within an hour of it and not ahead of it
            'stamp_age_ms_median': _median(age),
            'stamp_age_clock': 'sim time' if self._sim_time() else 'system time',
            'stamp_age_implausible': outputs.n_age_implausible,
            'depth_rate_hz': round(outputs.rate.mean_rate(first_image), 3),
            'expected_depth_rate_hz': s.expected_depth_rate,
            'points_rate_hz': round(outputs.points_rate.mean_rate(first_image), 3),
            'expected_points_rate_hz': s.expected_points_rate,
            'points_skipped_rate_cap': outputs.n_points_skipped,
            'processing_ms_median': _median(list(worker.process_ms)),
            'keyframe_ms_median': _median(list(worker.keyframe_ms)),
            'keyframe_ms_last': round(worker.last_keyframe_ms, 1) if worker.last_keyframe_ms is not None else 'n/a',
            # where the worker's time goes: the share of the last rate_window it spent processing images (near 1: it
            # is starved, and images are dropped as busy), and each stage's median over the last 50 keyframes
            'worker_busy_share': _share(worker.load.busy_share(time.monotonic(), s.rate_window)),
            'keyframe_stages_ms': worker.load.text(),
            'dropped_total': sum(dropped.values()),
        }
        for reason, n in sorted(dropped.items()):
            values[f'dropped.{reason}'] = n
        values.update(inputs.stream_loss.counts())          # lost.* (images lost before the callback), input_period_ms
        values['degenerate_episodes'] = worker.n_degenerate_episodes
        values['odometry_duplicates'] = inputs.pose_buffer.duplicates     # identical repeats, ignored
        for kind, n in sorted(node.faults.counts.items()):
            values[f'faults.{kind}'] = n
        values['filter_resets'] = est.pop('filter_resets')
        values['last_reset_reason'] = est.pop('last_reset_reason')
        values['output_resets'] = outputs.n_output_resets
        values['last_output_reset'] = outputs.last_output_reset
        values.update(est)
        values.update(self._graph_values())
        return values

    def _graph_values(self) -> dict:
        """Pose buffer, TF, rectification, the QoS and publishers of the inputs and the subscribers of the outputs."""
        node, inputs = self.node, self.node.inputs
        values = {'pose_buffer_size': len(inputs.pose_buffer),
                  # the worker waits for the odometry after an image's stamp, or for the camera mount on TF
                  'waiting_for_pose': inputs.odometry_wait.waiting,
                  'tf': node.outputs.tf.status() if node.outputs.tf is not None else 'off',
                  **inputs.extrinsic.values()}
        rect = inputs.rectifier
        values['rectification'] = 'off' if rect is None else \
            f'on ({rect.calibration.model}, K fx={rect.K[0, 0]:.2f} fy={rect.K[1, 1]:.2f})'
        for topic, n in sorted(node.qos_events.counts.items()):
            values[f'qos_incompatible.{topic}'] = n
        # publishers of the inputs that this node's subscriptions have matched (listed in the graph and matched by
        # the DDS reader: 0 means nothing arrives yet)
        for topic, sub in inputs.subscriptions.items():
            values[f'publishers.{topic}'] = min(sub.get_publisher_count(), inputs.matched.get(topic, 0))
        # subscribers of each output that its DDS writer has matched (it sends nothing to one it has not matched yet)
        for topic, n in node.outputs.matched.items():
            values[f'subscribers.{topic}'] = n
        for topic, reliability in inputs.reliability.items():
            values[f'input_qos.{topic}'] = reliability
        # how the colour image arrives (image_transport raw | compressed), where, and the decode time of compressed
        values['image_transport'] = inputs.image_transport
        values['image_topic'] = inputs.topic_name('image') or ''
        if inputs.image_transport == 'compressed':
            values['image_decode_ms_median'] = _median(list(inputs.decode_ms))
        return values

    def _drop_share_status(self, values: dict):
        """(level, problem or '') from the share of the images of the last rate_window that were lost in transport
        (lost.transport) or rejected as faulty (dropped.* other than busy: images replaced while the estimator
        was busy are the normal regime of a slow machine, reported but not warned about). Judged from 5 images
        on. A fault that is over (the last CLEAN_IMAGES_OVER images received all clean) is no WARN or ERROR any
        more: the share is still said, as over. Adds drop_share_window to `values`."""
        s = self.node.settings.node
        received = self.node.inputs.n_received
        now = time.monotonic()

        def number(v):
            try:
                return float(v)
            except (TypeError, ValueError):
                return 0.0
        faulty = sum(number(v) for k, v in values.items() if k.startswith('dropped.') and k != f'dropped.{BUSY}')
        lost = number(values.get('lost.transport', 0))     # every image lost before the callback (stream_loss)
        hist = self._share_history
        hist.append((now, received, faulty, lost))
        while len(hist) > 1 and now - hist[1][0] >= s.rate_window:
            hist.popleft()
        _t0, rec0, faulty0, lost0 = hist[0]
        seen = (received - rec0) + (lost - lost0)
        bad = (faulty - faulty0) + (lost - lost0)
        share = bad / seen if seen > 0 else 0.0
        values['drop_share_window'] = round(share, 3)
        if faulty + lost > self._bad_total:
            self._bad_total, self._received_at_bad = faulty + lost, received
        if seen < 5 or bad <= 0:
            return DiagnosticStatus.OK, ''
        clean = received - self._received_at_bad
        if clean >= CLEAN_IMAGES_OVER:
            return DiagnosticStatus.OK, (f'{share:.0%} of the last {int(seen)} images were lost in transport or '
                                         f'rejected as faulty, none of the {clean} since: over')
        text = (f'{share:.0%} of the last {int(seen)} images lost in transport or rejected as faulty '
                '(see lost.*, dropped.*)')
        if share > s.drop_error_share:
            return DiagnosticStatus.ERROR, text
        if share > s.drop_warn_share:
            return DiagnosticStatus.WARN, text
        return DiagnosticStatus.OK, ''

    def _rate_status(self, values: dict) -> list:
        """Frequency status per output against its expected rate: WARN below expected * (1 - rate_tolerance),
        ERROR when none came in the window; judged once images have arrived for a whole rate_window and while
        they still arrive (a stalled input has its own warning)."""
        s = self.node.settings.node
        first, last = self.node.inputs.first_image_mono, self.node.inputs.last_image_mono
        now = time.monotonic()
        if first is None or now - first < s.rate_window or now - last > 2.0:
            return []
        out = []
        checks = [('depth/image', values.get('depth_rate_hz', 0.0), s.expected_depth_rate)]
        if self.node.outputs.points.get_subscription_count() > 0:
            checks.append(('depth/points', values.get('points_rate_hz', 0.0), s.expected_points_rate))
        for name, rate, expected in checks:
            if expected > 0 and rate < expected * (1.0 - s.rate_tolerance):
                level = DiagnosticStatus.ERROR if rate == 0 else DiagnosticStatus.WARN
                out.append((level, f'{name} at {rate:.2f} Hz, expected {expected:g} Hz'))
        return out

    def _problems(self, values: dict):
        """(level, [problem]) of this tick."""
        level, problems = DiagnosticStatus.OK, []
        faults = self.node.faults
        exceptions = faults.counts[ESTIMATOR_EXCEPTION]
        if exceptions > self._last_exception_count:
            level = DiagnosticStatus.ERROR
            problems.append('estimator exceptions')
        self._last_exception_count = exceptions
        # faults that do not drop an image (camera_info, odometry jumps, incompatible QoS ...) warn when new; images
        # lost or rejected count by their share of the recent images (below)
        drop_kinds = set(self.node.dropped_counts())
        total_faults = sum(n for k, n in faults.counts.items() if k not in drop_kinds)
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
        if values.get('extrinsic_fault'):       # a TF loop or disagreeing publishers hold the mount: WARN throughout
            level = max(level, DiagnosticStatus.WARN)
            problems.append(str(values['extrinsic_fault']))
        if str(values.get('measurement_reason', '')).startswith('fallback'):
            level = max(level, DiagnosticStatus.WARN)
            problems.append('network weights missing: classical fallback')
        last_in = self.node.inputs.last_image_mono
        if last_in is None:
            problems.append('no images received yet')
        elif time.monotonic() - last_in > 2.0:
            level = max(level, DiagnosticStatus.WARN)
            problems.append(f'no image for {time.monotonic() - last_in:.1f} s')
        return level, problems

    def publish(self) -> None:
        try:
            values = self.values()
        except Exception as exc:
            values = {'error': f'{type(exc).__name__}: {exc}'}
        level, problems = self._problems(values)
        message = '; '.join(problems) if problems else 'ok'
        arr = DiagnosticArray()
        arr.header.stamp = self.node.get_clock().now().to_msg()
        name = f"{self.node.get_fully_qualified_name().lstrip('/')}: depth camera"
        arr.status = [DiagnosticStatus(level=level, name=name, message=message,
                                       hardware_id=f"dpv_sensor ({values.get('device', '?')})",
                                       values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])]
        self.pub.publish(arr)
