"""Replaying a bag through the node process, as `make demo` and the stream-table benchmark do (not a console
tool): start the node with a private DDS environment, wait until it is ready and matched, play the bag in lockstep
(each image held back until the node has finished the earlier ones) while recording its outputs, stop it with
SIGINT and report what happened (``run_node_replay``), plus the small pieces around it (``Steps`` progress lines,
``NodeMonitor`` on /diagnostics, ``render_scene``, ``parse_params``).

A camera image topic of image_transport's compressed kind (sensor_msgs/CompressedImage) is replayed to the node's
``image/compressed`` with ``image_transport: compressed``.

The bag's /tf_static and /tf (tf2_msgs/TFMessage) are played too, /tf_static with its recorded transient-local QoS,
before the first image: the node then finds the camera mount on TF (extrinsic_source auto, no T_base_camera typed).
A bag without them replays with extrinsic_source: parameter unless the caller chose one (``mount_params``): the
mount is T_base_camera, identity unless given, as before TF was read."""
from __future__ import annotations

import contextlib
import os
import pathlib
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional

from dpv_sensor import params as P
from dpv_sensor.ros.process_memory import proc_status_kib
from dpv_sensor.client.node_process import ClientNode, Launcher, launch_process, node_command

REPO = pathlib.Path(__file__).resolve().parents[2]
NS = 1_000_000_000

ODOM_RATE_HZ = 100.0

# node parameters the demo sets (a user's --params override them): reliable input so that no image is lost in
# transport, a deep input queue for the odometry bursts, and frequent diagnostics for the lockstep pacing
DEMO_NODE_PARAMS = {'input_reliability': 'reliable', 'input_depth': 50, 'diagnostics_period': 0.1}
OUTPUT_TOPICS = ('/depth/image', '/depth/camera_info', '/confidence/image', '/diagnostics')
DIAGNOSTICS_SUFFIX = ': depth camera'

class ReplayError(RuntimeError):
    """A replay step failed; the message says which and why."""


# --------------------------------------------------------------------------------------------------------------
# small helpers
# --------------------------------------------------------------------------------------------------------------
def _rel(path) -> str:
    """A path relative to the current directory when it lies inside it (shorter, copy-pasteable)."""
    p = pathlib.Path(path).resolve()
    try:
        return str(p.relative_to(pathlib.Path.cwd()))
    except ValueError:
        return str(p)



def _as_number(text, default=None):
    """A /diagnostics value (a string) as int or float; `default` when it is not a number ('n/a', missing)."""
    try:
        return int(text)
    except (TypeError, ValueError):
        pass
    try:
        return float(text)
    except (TypeError, ValueError):
        return default


def tf_topics(bag_topics: Dict[str, Any]) -> List[str]:
    """/tf_static and /tf when the bag has them as tf2_msgs/msg/TFMessage (bag_topics: ``rosbag_io.bag_topics``)."""
    from dpv_sensor.data import rosbag_io as R
    return [t for t in (R.TF_STATIC_TOPIC, R.TF_TOPIC) if bag_topics.get(t, ('',))[0] == R.TF_MESSAGE]


def mount_params(params: Dict[str, Any], tf: List[str]) -> Dict[str, Any]:
    """The node parameters for a bag with the TF topics `tf`: without any, extrinsic_source: parameter unless
    `params` choose it (no mount to look up; T_base_camera, identity unless given, as before TF was read)."""
    if tf or 'extrinsic_source' in params:
        return dict(params)
    return {**params, 'extrinsic_source': 'parameter'}


def bag_input_topics(bag_topics: Dict[str, Any], values: Dict[str, Any], *, image: Optional[str] = None,
                     camera_info: Optional[str] = None, odom: Optional[str] = None,
                     hints: Optional[Dict[str, str]] = None):
    """(topics, how each was chosen) of a recording to replay into the node with the settings ``values``: the image
    always, camera_info and odometry only where the node reads them from topics (None otherwise); found by message
    type unless named (``data.topic_detection.detect_input_topics``, whose BagError names what is missing, with
    ``hints`` on how to choose)."""
    from dpv_sensor.data.topic_detection import detect_input_topics
    need = ['image'] + (['camera_info'] if values['camera_info_source'] == 'topic' else []) + \
        (['odom'] if values['odometry'] == 'topic' else [])
    topics, how = detect_input_topics(bag_topics, image=image, camera_info=camera_info, odom=odom, need=need,
                                      options=hints)
    topics = {role: (t if role in need else None) for role, t in topics.items()}
    return topics, {role: h for role, h in how.items() if topics[role] is not None}


def parse_params(items: List[str]) -> Dict[str, Any]:
    """['preset=lite', 'fx=525', 'T_base_camera=[0,0,0,0,0,0,1]'] -> typed node parameters (params.SPECS).

    Accepts KEY=VALUE and KEY:=VALUE (``params.parse_assignments``); unknown names raise ValueError listing the
    known ones."""
    from dpv_sensor import params as P
    known = {s.name: s.default for s in P.SPECS}
    try:
        return P.parse_assignments(items or [], known)
    except ValueError as exc:
        raise ValueError(f'--params: {exc}'.replace('unknown configuration key', 'unknown node parameter')) from None


class Steps:
    """Numbered progress lines with the time of every step."""

    def __init__(self, total: int):
        self.total = total
        self.k = 0
        self.records: List[Dict[str, Any]] = []
        self._t0 = None

    @contextlib.contextmanager
    def step(self, name: str, what: str):
        self.k += 1
        print(f'[{self.k}/{self.total}] {what} ...', flush=True)
        t0 = time.perf_counter()
        rec = {'step': name, 'what': what, 'seconds': None, 'ok': False}
        self.records.append(rec)
        try:
            yield rec
            rec['ok'] = True
        finally:
            rec['seconds'] = round(time.perf_counter() - t0, 2)
            state = 'done' if rec['ok'] else 'FAILED'
            note = f" - {rec['note']}" if rec.get('note') else ''
            print(f'[{self.k}/{self.total}] {name}: {state} in {rec["seconds"]:.1f} s{note}', flush=True)

    def skip(self, name: str, why: str):
        self.k += 1
        self.records.append({'step': name, 'what': why, 'seconds': 0.0, 'ok': True, 'skipped': True})
        print(f'[{self.k}/{self.total}] {name}: skipped ({why})', flush=True)


# --------------------------------------------------------------------------------------------------------------
# watching the node
# --------------------------------------------------------------------------------------------------------------
class NodeMonitor:
    """The node's latest /diagnostics values (as a {key: str} dict), with a condition to wait on."""

    def __init__(self, node):
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=20, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)
        self.values: Dict[str, str] = {}
        self.level = None
        self.message = ''
        self.count = 0
        self.cv = threading.Condition()
        self.abort = threading.Event()
        self.sub = node.create_subscription(DiagnosticArray, '/diagnostics', self._on, qos)

    def _on(self, msg) -> None:
        for st in msg.status:
            if st.name.endswith(DIAGNOSTICS_SUFFIX) and st.hardware_id.startswith('dpv_sensor'):
                with self.cv:
                    self.values = {kv.key: kv.value for kv in st.values}
                    lvl = st.level
                    self.level = int.from_bytes(lvl, 'little') if isinstance(lvl, (bytes, bytearray)) else int(lvl)
                    self.message = st.message
                    self.count += 1
                    self.cv.notify_all()

    def get_int(self, key: str, default: int = 0) -> int:
        with self.cv:
            v = _as_number(self.values.get(key), None)
        return default if v is None else int(v)

    def accounted(self) -> int:
        """Images the node has finished with: estimated (frames_processed) or dropped for any reason."""
        with self.cv:
            return self._accounted(self.values)

    @staticmethod
    def _accounted(vals: Dict[str, str]) -> int:
        return int(_as_number(vals.get('frames_processed'), 0) or 0) + \
            int(_as_number(vals.get('dropped_total'), 0) or 0)

    def snapshot(self) -> Dict[str, str]:
        with self.cv:
            return dict(self.values)

    def wait_accounted(self, n: int, timeout: float) -> bool:
        """Block (another thread spins the executor) until at least `n` images are accounted for; False on timeout
        or abort."""
        deadline = time.monotonic() + timeout
        with self.cv:
            while True:
                if self.abort.is_set():
                    return False
                if self._accounted(self.values) >= n:
                    return True
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self.cv.wait(min(left, 0.2))


class GatedPublisher:
    """Wraps the player's image publisher: in lockstep mode each image waits until the node has accounted for all
    earlier images; stops the player after `max_images`. Everything else is the wrapped publisher's."""

    def __init__(self, pub, monitor: NodeMonitor, player, *, lockstep: bool, timeout: float,
                 max_images: int = 0, on_image=None, msg_class=None):
        self._pub = pub
        self._msg_class = msg_class          # the image's message class (sensor_msgs/Image by default)
        self._monitor = monitor
        self._player = player
        self._lockstep = lockstep
        self._timeout = timeout
        self._max = int(max_images or 0)
        self._on_image = on_image
        self.sent = 0
        self.timeouts = 0
        self.wait_s = 0.0
        self.sent_wall_ns: Dict[int, int] = {}   # image header stamp (ns) -> wall clock when it was published

    def publish(self, msg) -> None:
        if self._max and self.sent >= self._max:
            self._player.stop()
            return
        if self._lockstep and self.sent:
            t0 = time.monotonic()
            if not self._monitor.wait_accounted(self.sent, self._timeout) and not self._monitor.abort.is_set():
                self.timeouts += 1
                print(f'\nwarning: the node has not finished image {self.sent - 1} after {self._timeout:g} s; '
                      'sending the next one anyway', file=sys.stderr, flush=True)
            self.wait_s += time.monotonic() - t0
        if self._monitor.abort.is_set():
            self._player.stop()
            return
        stamp_ns = self._stamp_ns(msg, self._msg_class)
        self._pub.publish(msg)
        if stamp_ns is not None:
            self.sent_wall_ns[stamp_ns] = time.time_ns()
        self.sent += 1
        if self._on_image is not None:
            self._on_image(self.sent)

    @staticmethod
    def _stamp_ns(msg, msg_class=None) -> Optional[int]:
        """Header stamp of an image given as a message or as CDR bytes (what the player publishes)."""
        try:
            if isinstance(msg, (bytes, bytearray, memoryview)):
                from rclpy.serialization import deserialize_message
                from sensor_msgs.msg import Image
                msg = deserialize_message(bytes(msg), msg_class or Image)
            return msg.header.stamp.sec * NS + msg.header.stamp.nanosec
        except Exception:
            return None

    def __getattr__(self, name):
        return getattr(self._pub, name)


# --------------------------------------------------------------------------------------------------------------
# steps
# --------------------------------------------------------------------------------------------------------------
def render_scene(seq_dir: pathlib.Path, seed: int, frames: int, width: int, height: int, progress: bool):
    from dpv_sensor.data.sequence import write_sequence
    from dpv_sensor.data.synthetic import render_sequence
    seq = render_sequence(seed, frames, width=width, height=height, progress=progress)
    write_sequence(seq_dir, seq, lossless=True, progress=progress)
    return seq



@dataclass
class ReplayResult:
    images_in_bag: int = 0
    images_sent: int = 0
    messages_published: int = 0
    wall_s: float = 0.0
    lockstep: bool = True
    rate: float = 1.0
    wait_s: float = 0.0
    timeouts: int = 0
    recorded: Dict[str, int] = field(default_factory=dict)
    diagnostics: Dict[str, str] = field(default_factory=dict)
    node_exit_code: Optional[int] = None
    node_peak_rss_mib: Optional[float] = None
    node_start_s: float = 0.0
    node_stop_s: float = 0.0
    node_log: str = ''
    node_command: List[str] = field(default_factory=list)
    # how the node was fed the bag's image topic (raw | compressed)
    image_transport: str = field(default_factory=lambda: P.default('image_transport'))
    warnings: List[str] = field(default_factory=list)
    e2e_ms: Dict[str, Any] = field(default_factory=dict)


def end_to_end_latency(output_bag, sent_wall_ns: Dict[int, int]) -> Dict[str, Any]:
    """Per depth output: wall time from publishing its image into the graph to recording its depth image (the
    recorder's record time is its receipt time). Median / p95 / max in ms over the outputs."""
    import numpy as np
    from dpv_sensor.ros import msgs as M
    from dpv_sensor.data import rosbag_io as R
    lat = []
    for _t, _ty, log_ns, msg in R.read_messages(output_bag, ['/depth/image']):
        sent = sent_wall_ns.get(M.stamp_to_ns(msg.header.stamp))
        if sent is not None:
            lat.append((log_ns - sent) / 1e6)
    if not lat:
        return {'outputs': 0}
    return {'outputs': len(lat), 'median': float(np.median(lat)), 'p95': float(np.percentile(lat, 95)),
            'max': float(np.max(lat))}


def run_node_replay(steps: Steps, input_bag: pathlib.Path, output_bag: pathlib.Path, *, topics: Dict[str, str],
                    params: Dict[str, Any], log_dir: pathlib.Path, lockstep: bool, rate: float,
                    start_timeout: float, frame_timeout: float, max_images: int, progress: bool,
                    launch: Optional[Launcher] = None) -> ReplayResult:
    """Steps 3-5: start the node, replay `input_bag` through it while recording its outputs, stop it.

    ``launch(command, env, log_path)`` starts the node's command line as its own process, output to ``log_path``,
    and returns a handle with :class:`subprocess.Popen`'s ``pid``, ``poll``, ``returncode``, ``send_signal``,
    ``wait`` and ``kill``; by default :func:`launch_process` (a test suite forks it from a process that has already
    made the imports)."""
    opts = ReplayOptions(topics=topics, lockstep=lockstep, rate=rate, start_timeout=start_timeout,
                         frame_timeout=frame_timeout, max_images=max_images, progress=progress,
                         launch=launch or launch_process)
    replay = _NodeReplay(steps, input_bag, output_bag, params, log_dir, opts)
    try:
        with steps.step('node', 'start the node process and wait for its subscriptions') as rec:
            rec['note'] = replay.start_node()
        total = replay.res.images_in_bag if not max_images else min(max_images, replay.res.images_in_bag)
        mode = 'lockstep (each image waits for the previous one)' if lockstep else f'{rate:g}x real time'
        with steps.step('replay', f'replay {total} images through the node, {mode}, recording its outputs') as rec:
            rec['note'] = replay.replay(total)
        with steps.step('stop', 'stop the node with SIGINT') as rec:
            replay.stop_node(rec)
    finally:
        replay.close()
    return replay.res


@dataclass
class ReplayOptions:
    """How :func:`run_node_replay` drives the node: the topic of each role (image, camera_info, odom, ...),
    lockstep or ``rate`` x real time, the timeouts (s), an image limit (0: all) and a progress bar."""
    topics: Dict[str, str]
    lockstep: bool
    rate: float
    start_timeout: float
    frame_timeout: float
    max_images: int
    progress: bool
    launch: 'Launcher'

    @property
    def play_topics(self) -> List[str]:
        return [t for t in (self.topics.get('image'), self.topics.get('camera_info'), self.topics.get('odom')) if t]


class _NodeReplay:
    """One replay session: the node process, the client node (monitor, recorder, player) and the result."""

    def __init__(self, steps: Steps, input_bag: pathlib.Path, output_bag: pathlib.Path, params: Dict[str, Any],
                 log_dir: pathlib.Path, opts: ReplayOptions):
        from dpv_sensor.data import rosbag_io as R
        from dpv_sensor.data.topic_detection import image_transport_of
        self.steps, self.input_bag, self.output_bag, self.opts = steps, input_bag, output_bag, opts
        self.res = ReplayResult(lockstep=opts.lockstep, rate=opts.rate)
        bag_topics = R.bag_topics(input_bag)
        self.res.images_in_bag = bag_topics[opts.topics['image']][1]
        # the bag's image type decides the node's image_transport: a CompressedImage topic goes to image/compressed
        transport = self.res.image_transport = image_transport_of(bag_topics, opts.topics['image'])
        params = {**params, 'image_transport': transport}
        remaps = {('image/compressed' if name == 'image' and transport == 'compressed' else name): t
                  for name, t in opts.topics.items() if t}
        self.tf_topics = tf_topics(bag_topics)         # played as they are (absolute names, not remapped)
        self.cmd = node_command(mount_params(params, self.tf_topics), remaps)
        self.res.node_command = self.cmd
        self.log_path = log_dir / 'node.log'
        self.proc = None
        self.client = self.node = self.executor = self.recorder = self.monitor = self.player = None
        self.t_start = time.perf_counter()
        self.peak_rss = 0

    # -- helpers ------------------------------------------------------------------------------------------------
    def spin_until(self, cond, timeout: float) -> bool:
        """Spin the client until ``cond()`` holds, the node exits or ``timeout`` s pass; returns ``cond()``."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if cond():
                return True
            if self.proc.poll() is not None:
                return cond()
            self.executor.spin_once(timeout_sec=0.05)
        return cond()

    def node_died(self) -> str:
        """The error message of a node that exited: its exit code and the tail of its log."""
        tail = self._node_log().strip().splitlines()[-15:]
        return (f'the node exited with code {self.proc.returncode} (log: {_rel(self.log_path)}):\n    ' +
                '\n    '.join(tail))

    def _node_log(self) -> str:
        """What the node process wrote (a launcher whose process failed before opening its log wrote nothing)."""
        return self.log_path.read_text(errors='replace') if self.log_path.exists() else '(the node wrote no log)'

    # -- 3. start the node --------------------------------------------------------------------------------------
    def start_node(self) -> str:
        """Start the node process and the client, wait until the node is ready, subscribed and publishing."""
        from dpv_sensor.client.ros_io import BagPlayer, BagRecorder
        env = dict(os.environ)
        env['PYTHONPATH'] = os.pathsep.join([str(REPO)] + [p for p in env.get('PYTHONPATH', '').split(os.pathsep)
                                                          if p])
        env.setdefault('PYTHONUNBUFFERED', '1')
        self.proc = self.opts.launch(self.cmd, env, self.log_path)
        # Ctrl-C stays a KeyboardInterrupt here and reaches the node process as a SIGINT: it stops by itself
        self.client = ClientNode('dpv_demo')
        self.node, self.executor = self.client.node, self.client.executor
        from rclpy.logging import LoggingSeverity
        self.node.get_logger().set_level(LoggingSeverity.WARN)   # the recorder's "recording ..." lines
        self.monitor = NodeMonitor(self.node)
        self.recorder = BagRecorder(self.node, self.output_bag, OUTPUT_TOPICS, overwrite=True)
        self.player = BagPlayer(self.node, self.input_bag, rate=self.opts.rate,
                                topics=self.opts.play_topics + self.tf_topics)
        self._wait_estimator()
        self._wait_subscribed()
        self._wait_publishing()
        self._wait_recorder_matched()
        self.res.node_start_s = round(time.perf_counter() - self.t_start, 2)
        d = self.monitor.snapshot()
        return (f"pid {self.proc.pid}, measurement {d.get('measurement_model')}, device {d.get('device')}, "
                f"filter {d.get('filter_mode')}")

    def _wait_estimator(self) -> None:
        monitor, start_timeout = self.monitor, self.opts.start_timeout
        ready = self.spin_until(lambda: monitor.count > 0 and monitor.values.get('measurement_model') not in
                                (None, 'starting'), start_timeout)
        if self.proc.poll() is not None:
            raise ReplayError(self.node_died())
        if not ready:
            raise ReplayError(f'the node did not report a built estimator within {start_timeout:g} s '
                              f'(log: {_rel(self.log_path)})')

    def _wait_subscribed(self) -> None:
        """The node subscribed to the played topics, and its readers matched the player's writers (DDS matching
        is not symmetric: what the player sends before the node's reader matched it is lost, e.g. the first
        camera_info messages)."""
        opts, monitor = self.opts, self.monitor
        wait_s = max(10.0, opts.start_timeout)
        missing = self.player.wait_for_subscribers(opts.play_topics, timeout=wait_s,
                                                   spin=lambda t: self.executor.spin_once(timeout_sec=t))
        if missing:
            raise ReplayError(f'the node did not subscribe to {missing} within {wait_s:g} s '
                              f'(log: {_rel(self.log_path)})')
        roles = [r for r in ('image', 'camera_info', 'odom') if opts.topics.get(r)]
        if not self.spin_until(lambda: all(monitor.get_int(f'publishers.{r}') >= 1 for r in roles), wait_s):
            unmatched = [r for r in roles if monitor.get_int(f'publishers.{r}') < 1]
            raise ReplayError(f"the node's subscriptions did not match the player's {unmatched} publishers "
                              f'within {wait_s:g} s (log: {_rel(self.log_path)})')
        # TF: the node subscribes it only when it looks the camera mount up there; then its reader should match
        # the player's (latched) /tf_static before the first image, so the first images find the mount
        listened = [t for t in self.tf_topics if self.node.count_subscribers(t) > 0]
        if listened:
            self.player.wait_for_subscribers(listened, timeout=wait_s,
                                             spin=lambda t: self.executor.spin_once(timeout_sec=t))

    def _wait_publishing(self) -> None:
        self.spin_until(lambda: not self.recorder.poll(), 10.0)
        still = self.recorder.poll()
        if still:
            raise ReplayError(f'the node does not publish {still} (log: {_rel(self.log_path)})')

    def _wait_recorder_matched(self) -> None:
        """The recorder's readers and the node's writers of the recorded outputs have matched each other (the node's
        /diagnostics counts its matched subscribers): a reliable volatile writer sends nothing to a reader it has not
        matched yet, so the first outputs would be lost."""
        monitor, subs = self.monitor, self.recorder.subscriptions
        outputs = [t for t in OUTPUT_TOPICS if t != '/diagnostics']
        wait_s = max(10.0, self.opts.start_timeout)

        def matched(t: str) -> bool:
            return subs[t].get_publisher_count() >= 1 and monitor.get_int(f'subscribers.{t.lstrip("/")}') >= 1
        if not self.spin_until(lambda: all(matched(t) for t in outputs), wait_s):
            raise ReplayError(f"the node's publishers of {[t for t in outputs if not matched(t)]} did not match the "
                              f'recorder within {wait_s:g} s (log: {_rel(self.log_path)})')

    # -- 4. replay and record -----------------------------------------------------------------------------------
    def replay(self, total: int) -> str:
        """Play the bag through the node (gated in lockstep), wait for the last outputs, collect the figures."""
        opts, monitor, recorder, res = self.opts, self.monitor, self.recorder, self.res
        bar = None
        if opts.progress:
            from tqdm import tqdm
            bar = tqdm(total=total, unit='img', desc='replay', leave=False, dynamic_ncols=True)

        def on_image(n):
            if bar is not None:
                bar.update(1)
                bar.set_postfix(outputs=recorder.counts.get('/depth/image', 0),
                                keyframes=monitor.values.get('estimator_keyframes', '?'), refresh=False)

        gate = GatedPublisher(self.player.publishers[opts.topics['image']], monitor, self.player,
                              lockstep=opts.lockstep, timeout=opts.frame_timeout, max_images=opts.max_images,
                              on_image=on_image, msg_class=self.player.classes[opts.topics['image']])
        self.player.publishers[opts.topics['image']] = gate
        t0 = time.perf_counter()
        stats = self._play_while_watching()
        res.images_sent = gate.sent
        res.messages_published = stats.published
        res.wait_s = round(gate.wait_s, 2)
        res.timeouts = gate.timeouts
        self._wait_last_outputs(gate)
        res.wall_s = round(time.perf_counter() - t0, 2)
        if bar is not None:
            bar.close()
        res.diagnostics = monitor.snapshot()
        hwm = proc_status_kib(self.proc.pid, 'VmHWM')
        res.node_peak_rss_mib = round(max(self.peak_rss, hwm or 0) / 1024.0, 1)
        recorder.close()
        res.recorded = dict(recorder.counts)
        res.e2e_ms = end_to_end_latency(self.output_bag, gate.sent_wall_ns)
        d = res.diagnostics
        self._warn_about_replay(gate)
        return (f"{gate.sent} images, {d.get('estimator_keyframes', '?')} keyframes, "
                f"{res.recorded.get('/depth/image', 0)} depth outputs recorded, "
                f"{d.get('dropped_total', '?')} dropped")

    def _play_while_watching(self):
        """Play the bag in a thread while this one spins the client and watches the node (memory, exit)."""
        box: Dict[str, Any] = {}
        player = self.player

        def play():
            try:
                box['stats'] = player.play(progress=False)
            except BaseException as exc:   # reported by the main thread
                box['error'] = exc
        thread = threading.Thread(target=play, name='demo_player', daemon=True)
        thread.start()
        while thread.is_alive():
            self.executor.spin_once(timeout_sec=0.05)
            rss = proc_status_kib(self.proc.pid, 'VmRSS')
            self.peak_rss = max(self.peak_rss, rss or 0)
            if self.proc.poll() is not None:
                self.monitor.abort.set()
                player.stop()
                thread.join(5.0)
                raise ReplayError(self.node_died())
        thread.join()
        if 'error' in box:
            raise ReplayError(f'playing the bag failed: {type(box["error"]).__name__}: {box["error"]}')
        return box['stats']

    def _wait_last_outputs(self, gate: 'GatedPublisher') -> None:
        """The last images: wait until the node has finished them and every output is recorded."""
        monitor, recorder = self.monitor, self.recorder
        self.spin_until(lambda: monitor.accounted() >= gate.sent, self.opts.frame_timeout)

        def all_recorded():
            n = monitor.get_int('outputs_published', -1)
            c = recorder.counts
            return n >= 0 and all(c.get(t, 0) >= n for t in OUTPUT_TOPICS[:3])
        self.spin_until(all_recorded, 30.0)
        self.spin_until(lambda: False, 0.3)   # one more diagnostics message for the final figures

    def _warn_about_replay(self, gate: 'GatedPublisher') -> None:
        monitor, res = self.monitor, self.res
        d = res.diagnostics
        if monitor.accounted() < gate.sent:
            res.warnings.append(f'the node finished only {monitor.accounted()} of {gate.sent} images')
        n_out = monitor.get_int('outputs_published', -1)
        if res.recorded.get('/depth/image', 0) < n_out:
            res.warnings.append(f"recorded {res.recorded.get('/depth/image', 0)} depth images but the node "
                                f'published {n_out}')
        dropped = monitor.get_int('dropped_total', 0)
        if dropped:
            reasons = ', '.join(f'{k[8:]}: {v}' for k, v in d.items() if k.startswith('dropped.'))
            res.warnings.append(f'the node dropped {dropped} images ({reasons})')
        if gate.timeouts:
            res.warnings.append(f'{gate.timeouts} images were sent before the node finished the previous one '
                                f'(--frame-timeout {self.opts.frame_timeout:g} s)')

    # -- 5. stop ------------------------------------------------------------------------------------------------
    def stop_node(self, rec: Dict[str, Any]) -> None:
        """Stop the node with SIGINT (killed after 30 s) and read its log; the exit code goes to the step's note."""
        import signal
        import subprocess
        res, proc = self.res, self.proc
        t0 = time.perf_counter()
        proc.send_signal(signal.SIGINT)
        try:
            res.node_exit_code = proc.wait(timeout=30.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
            res.node_exit_code = None
        res.node_stop_s = round(time.perf_counter() - t0, 2)
        res.node_log = self._node_log()
        rec['note'] = f'exit code {res.node_exit_code}'
        if res.node_exit_code != 0:
            raise ReplayError(f'the node did not stop cleanly on SIGINT (exit code {res.node_exit_code}; log: '
                              f'{_rel(self.log_path)})')
        if 'Traceback' in res.node_log:
            res.warnings.append(f'the node log has a Python traceback: {_rel(self.log_path)}')

    def close(self) -> None:
        """Release everything, whatever step failed: the player, the recorder, the node process, the client."""
        if self.monitor is not None:
            self.monitor.abort.set()          # releases a player thread waiting in the gate
        if self.player is not None:
            self.player.stop()
        if self.recorder is not None and not self.recorder.closed:
            self.recorder.close()
        if self.proc is not None and self.proc.poll() is None:
            import signal
            import subprocess
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=20.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if self.client is not None:
            self.client.close()
