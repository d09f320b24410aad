"""Shared ROS plumbing of the tools (not a console tool): replaying and recording bags over a live graph
(``BagPlayer``, ``BagRecorder``, ``qos_from_bag``), collecting a node's outputs by stamp (``OutputCollector``)
and a private DDS environment for a tool run (``private_ros_env``). The tools (bag, demo, soak, bench) and the
integration tests import these from here; no tool imports another tool.
"""
from __future__ import annotations

import os
import pathlib
import random
import threading
import time
from dataclasses import dataclass, field
from typing import Dict, Optional

from dpv_sensor.data import rosbag_io as R

NS = 1_000_000_000


# --------------------------------------------------------------------------------------------------------------
# QoS helpers
# --------------------------------------------------------------------------------------------------------------
def qos_from_bag(profiles, override_reliability: str | None = None, depth: int | None = None):
    """rclpy QoSProfile for a publisher replaying a topic: the first recorded offered profile (reliability,
    durability, history depth), reliable / volatile / keep-last 10 when the bag recorded none."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    reliability, durability, hist_depth = ReliabilityPolicy.RELIABLE, DurabilityPolicy.VOLATILE, 10
    if profiles:
        p = profiles[0]
        if p.reliability.name == 'BEST_EFFORT':
            reliability = ReliabilityPolicy.BEST_EFFORT
        if p.durability.name == 'TRANSIENT_LOCAL':
            durability = DurabilityPolicy.TRANSIENT_LOCAL
        if p.history.name == 'KEEP_LAST' and p.depth > 0:
            hist_depth = int(p.depth)
    if override_reliability:
        reliability = {'reliable': ReliabilityPolicy.RELIABLE,
                       'best_effort': ReliabilityPolicy.BEST_EFFORT}[override_reliability]
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=int(depth or hist_depth), reliability=reliability,
                      durability=durability)


# --------------------------------------------------------------------------------------------------------------
# play
# --------------------------------------------------------------------------------------------------------------
@dataclass
class PlaybackStats:
    published: int = 0
    per_topic: dict = field(default_factory=dict)
    loops: int = 0
    wall_s: float = 0.0
    late_ms_max: float = 0.0          # how far behind schedule the player fell at worst
    stopped: bool = False
    # with rebase_stamps: the stamp (ns) each image was published with, and the bag's original stamp
    rebased: list = field(default_factory=list)


class BagPlayer:
    """Replays a rosbag2 into the graph with `node`'s publishers (one per bag topic, the recorded QoS).

    rate: playback speed factor (1 = real time). topics: only these bag topics. remap: {bag topic: published
    topic}. rebase_stamps: header stamps are shifted so the first message carries "now" (wall clock) and later
    ones keep their offsets (divided by the rate) — the node then sees live-looking stamps (latency measurements,
    loops without time going backwards). loop: play again from the start (with rebase_stamps, time keeps
    increasing across loops).
    """

    def __init__(self, node, bag_path, *, rate: float = 1.0, topics=None, remap=None,
                 rebase_stamps: bool = False, loop: bool = False, reliability: str | None = None,
                 qos_depth: int | None = None):
        from dpv_sensor.ros.msgs import ros_message_class
        if rate <= 0:
            raise ValueError(f'rate must be > 0, got {rate}')
        self.node = node
        self.path = pathlib.Path(bag_path)
        self.rate = float(rate)
        self.rebase_stamps = rebase_stamps
        self.loop = loop
        all_topics = R.bag_topics(self.path)
        self.topics = list(all_topics) if not topics else list(topics)
        missing = [t for t in self.topics if t not in all_topics]
        if missing:
            raise R.BagError(f'{self.path}: no topic {missing} (topics: {sorted(all_topics)})')
        self.remap = dict(remap or {})
        qos = R.bag_qos(self.path)
        self.types = {t: all_topics[t][0] for t in self.topics}
        self.counts = {t: all_topics[t][1] for t in self.topics}
        self.classes = {t: ros_message_class(self.types[t]) for t in self.topics}
        # DDS "publication matched" counts per topic, from the publishers' matched events: a subscription that the
        # graph lists is not yet necessarily matched by our writer, and a volatile one would miss what we send
        # before that. The events are delivered by whatever executor spins `node`.
        self.matched = {t: 0 for t in self.topics}
        self.publishers = {t: node.create_publisher(self.classes[t], self.remap.get(t, t),
                                                    qos_from_bag(qos.get(t), reliability, qos_depth),
                                                    event_callbacks=self._matched_callbacks(t))
                           for t in self.topics}
        self.stop_event = threading.Event()
        self.on_publish = None   # optional callback(topic, msg_or_None, bag_stamp_ns, published_stamp_ns)

    @property
    def total_messages(self) -> int:
        return sum(self.counts.values())

    def published_topic(self, bag_topic: str) -> str:
        return self.publishers[bag_topic].topic_name

    def _matched_callbacks(self, topic: str):
        from rclpy.event_handler import PublisherEventCallbacks

        def on_matched(info) -> None:
            self.matched[topic] = int(info.current_count)
        return PublisherEventCallbacks(matched=on_matched)

    def subscriber_count(self, topic: str) -> int:
        """Subscriptions on a bag topic that are both in the graph and matched by its publisher (DDS)."""
        return min(self.publishers[topic].get_subscription_count(), self.matched[topic])

    def wait_for_subscribers(self, topics=None, timeout: float = 10.0, spin=None, min_count: int = 1) -> list[str]:
        """Wait until every topic in `topics` (bag names; default: all) has at least `min_count` subscriptions
        matched by its publisher, at most `timeout` s. Returns the topics still short of that (empty list: all
        matched). The matched events arrive through the executor of the player's node: pass `spin` (e.g.
        ``lambda t: executor.spin_once(timeout_sec=t)``) unless another thread spins it."""
        wanted = list(topics) if topics else list(self.topics)
        deadline = time.monotonic() + timeout
        while True:
            missing = [t for t in wanted if self.subscriber_count(t) < min_count]
            if not missing or time.monotonic() >= deadline or self.stop_event.is_set():
                return missing
            if spin is not None:
                spin(0.05)
            else:
                time.sleep(0.05)

    def stop(self) -> None:
        self.stop_event.set()

    def play(self, progress: bool = False, duration: float | None = None) -> PlaybackStats:
        """Publish every message at its record time / rate; returns statistics. Blocks until done, stopped
        (stop()) or `duration` wall seconds have passed."""
        stats = PlaybackStats(per_topic={t: 0 for t in self.topics})
        bar = None
        if progress:
            from tqdm import tqdm
            bar = tqdm(total=None if self.loop else self.total_messages, unit='msg', desc=f'playing {self.path.name}')
        t_start = time.monotonic()
        wall_deadline = None if duration is None else t_start + duration
        try:
            while True:
                if not self._play_pass(stats, bar, wall_deadline):
                    stats.stopped = True
                    return stats
                stats.loops += 1
                if not self.loop:
                    return stats
        finally:
            stats.wall_s = time.monotonic() - t_start
            if bar is not None:
                bar.close()

    def _play_pass(self, stats: PlaybackStats, bar, wall_deadline: float | None) -> bool:
        """One pass through the bag, each message published when due; False when stopped before the end."""
        clock = _PassClock(start_mono=time.monotonic(), start_wall_ns=time.time_ns())
        for topic, _type, log_ns, raw in R.read_messages(self.path, self.topics, raw=True):
            if clock.first_log_ns is None:
                clock.first_log_ns = log_ns
            due = clock.start_mono + (log_ns - clock.first_log_ns) / NS / self.rate
            if not self._wait_until(due, wall_deadline):
                return False
            stats.late_ms_max = max(stats.late_ms_max, (time.monotonic() - due) * 1000.0)
            if not self._publish(topic, log_ns, raw, clock):
                return False
            stats.published += 1
            stats.per_topic[topic] += 1
            if bar is not None:
                bar.update(1)
        return True

    def _stop_requested(self, now: float, wall_deadline: float | None) -> bool:
        """stop() was called, the duration is over, or Ctrl-C shut the context down."""
        return self.stop_event.is_set() or (wall_deadline is not None and now >= wall_deadline) \
            or not self.node.context.ok()

    def _wait_until(self, due: float, wall_deadline: float | None) -> bool:
        """Sleep until the monotonic time `due`; False when stopped first."""
        while True:
            now = time.monotonic()
            if self._stop_requested(now, wall_deadline):
                return False
            if now >= due:
                return True
            time.sleep(min(due - now, 0.05))

    def _publish(self, topic: str, log_ns: int, raw: bytes, clock: _PassClock) -> bool:
        """Publish one bag message (with rebase_stamps: deserialized, its header stamp rebased); False when the
        context was shut down while publishing (Ctrl-C)."""
        pub = self.publishers[topic]
        try:
            if self.rebase_stamps:
                pub.publish(self._rebased(topic, raw, clock))
            else:
                pub.publish(raw)
                if self.on_publish is not None:
                    self.on_publish(topic, None, log_ns, log_ns)
        except Exception:
            if not self.node.context.ok():
                return False
            raise
        return True

    def _rebased(self, topic: str, raw: bytes, clock: _PassClock):
        """The message with its header stamp moved to the pass's wall-clock start plus its offset / rate."""
        from rclpy.serialization import deserialize_message
        from dpv_sensor.ros.msgs import make_header, stamp_to_ns
        msg = deserialize_message(raw, self.classes[topic])
        if hasattr(msg, 'header'):
            old = stamp_to_ns(msg.header.stamp)
            if clock.first_stamp_ns is None:
                clock.first_stamp_ns = old
            new = clock.start_wall_ns + int((old - clock.first_stamp_ns) / self.rate)
            msg.header = make_header(new, msg.header.frame_id)
            if self.on_publish is not None:
                self.on_publish(topic, msg, old, new)
        return msg


@dataclass
class _PassClock:
    """Time references of one pass through the bag: when it started (monotonic, wall ns), the first message's
    record time and the first header stamp (for rebasing)."""
    start_mono: float
    start_wall_ns: int
    first_log_ns: int | None = None
    first_stamp_ns: int | None = None


# --------------------------------------------------------------------------------------------------------------
# record
# --------------------------------------------------------------------------------------------------------------
class BagRecorder:
    """Subscribes to topics (raw CDR, QoS matched to the publishers) and writes them to a bag as they arrive.

    topics: names to record (types are looked up in the graph; a topic that is not advertised yet is picked up
    when it appears while `poll()` runs). all_topics: record everything that appears. The record time of each
    message is its receipt time (node clock).
    """

    def __init__(self, node, out_path, topics=(), all_topics: bool = False, storage: str = 'mcap',
                 overwrite: bool = False, depth: int = 100):
        self.node = node
        self.writer = R.BagWriter(out_path, storage=storage, overwrite=overwrite)
        self.wanted = [self._resolve(t) for t in topics]
        self.all_topics = all_topics
        self.depth = depth
        self.subscriptions = {}
        self._qos = {}
        self._lock = threading.Lock()
        self.closed = False

    def _resolve(self, topic: str) -> str:
        return topic if topic.startswith('/') else '/' + topic

    def _qos_for(self, topic: str):
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
        infos = self.node.get_publishers_info_by_topic(topic)
        reliable = bool(infos) and all(i.qos_profile.reliability == ReliabilityPolicy.RELIABLE for i in infos)
        return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=self.depth,
                          reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
                          durability=DurabilityPolicy.VOLATILE), reliable

    def poll(self) -> list[str]:
        """Subscribe to wanted topics that have appeared in the graph; returns the ones still missing."""
        from dpv_sensor.ros.msgs import ros_message_class
        graph = dict(self.node.get_topic_names_and_types())
        targets = list(graph) if self.all_topics else self.wanted
        for topic in targets:
            if topic in self.subscriptions or topic not in graph:
                continue
            if self.all_topics and topic in ('/rosout', '/parameter_events'):
                continue
            msgtype = graph[topic][0]
            qos, reliable = self._qos_for(topic)
            if not self.node.get_publishers_info_by_topic(topic):
                continue
            cls = ros_message_class(msgtype)

            def callback(data, topic=topic, msgtype=msgtype):
                self._write(topic, msgtype, data)
            self.subscriptions[topic] = self.node.create_subscription(cls, topic, callback, qos, raw=True)
            self._qos[topic] = R.qos_profile(reliable=reliable, depth=self.depth)
            self.node.get_logger().info(f'recording {topic} [{msgtype}] ({"reliable" if reliable else "best effort"})')
        return [t for t in self.wanted if t not in self.subscriptions]

    def _write(self, topic, msgtype, data: bytes) -> None:
        with self._lock:
            if self.closed:
                return
            self.writer.write(topic, msgtype, data, self.node.get_clock().now().nanoseconds, self._qos.get(topic))

    @property
    def counts(self) -> dict:
        return dict(self.writer.counts)

    def close(self) -> None:
        with self._lock:
            if not self.closed:
                self.closed = True
                self.writer.close()
        for sub in self.subscriptions.values():
            self.node.destroy_subscription(sub)
        self.subscriptions.clear()


# --------------------------------------------------------------------------------------------------------------
# watching a node's outputs
# --------------------------------------------------------------------------------------------------------------
@dataclass
class Received:
    """Everything that arrived for one output stamp (messages kept only with keep_messages)."""
    stamp_ns: int
    frame_id: str = ''
    depth: object = None
    confidence: object = None
    camera_info: object = None
    points: object = None
    depth_wall_ns: int | None = None
    topics: set = field(default_factory=set)


class OutputCollector:
    """Subscribes (reliable) to a node's outputs under `namespace` and groups them by header stamp.

    Topics: depth/image, depth/camera_info, confidence/image, optionally depth/points, and /diagnostics (the latest
    status of the node named `diagnostics_name` is kept in `diagnostics`, as a {key: value} dict).
    """

    def __init__(self, node, namespace: str = '', points: bool = False, keep_messages: bool = True,
                 diagnostics_name: str = 'dpv_sensor: depth camera', depth: int = 50):
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import CameraInfo, Image, PointCloud2
        self.node = node
        ns = namespace.rstrip('/')
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)
        self.keep = keep_messages
        self.by_stamp: dict[int, Received] = {}
        self.order: list[int] = []               # depth stamps in arrival order
        self.latency_ms: list[float] = []         # depth receipt (wall) - stamp, for rebased live stamps
        self.diagnostics: dict = {}
        self.diagnostics_level = None
        self.diagnostics_message = ''
        self.diagnostics_count = 0
        self.diagnostics_name = diagnostics_name
        self._lock = threading.Lock()
        self.subs = [
            node.create_subscription(Image, f'{ns}/depth/image', lambda m: self._on(m, 'depth'), qos),
            node.create_subscription(Image, f'{ns}/confidence/image', lambda m: self._on(m, 'confidence'), qos),
            node.create_subscription(CameraInfo, f'{ns}/depth/camera_info', lambda m: self._on(m, 'camera_info'), qos),
            node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, qos),
        ]
        self.points_sub = None
        if points:
            self.points_sub = node.create_subscription(PointCloud2, f'{ns}/depth/points',
                                                       lambda m: self._on(m, 'points'), qos)

    def _on(self, msg, kind: str) -> None:
        now = time.time_ns()
        stamp = msg.header.stamp.sec * NS + msg.header.stamp.nanosec
        with self._lock:
            rec = self.by_stamp.get(stamp)
            if rec is None:
                rec = self.by_stamp[stamp] = Received(stamp, msg.header.frame_id)
            rec.topics.add(kind)
            if self.keep:
                setattr(rec, kind, msg)
            if kind == 'depth':
                rec.depth_wall_ns = now
                self.order.append(stamp)
                self.latency_ms.append((now - stamp) / 1e6)
            if not self.keep and len(self.by_stamp) > 1000:   # long runs: keep the bookkeeping bounded
                for k in list(self.by_stamp)[:500]:
                    del self.by_stamp[k]

    def _on_diag(self, msg) -> None:
        for st in msg.status:
            if st.name == self.diagnostics_name:
                with self._lock:
                    self.diagnostics = {kv.key: kv.value for kv in st.values}
                    self.diagnostics_level = int.from_bytes(st.level, 'little') if isinstance(st.level, bytes) \
                        else int(st.level)
                    self.diagnostics_message = st.message
                    self.diagnostics_count += 1

    def diag_int(self, key: str, default: int = 0) -> int:
        try:
            return int(self.diagnostics.get(key, default))
        except (TypeError, ValueError):
            return default

    @property
    def depth_count(self) -> int:
        return len(self.order)

    def complete(self) -> list[Received]:
        """Outputs for which depth, confidence and camera_info all arrived, in arrival order of the depth."""
        return [self.by_stamp[s] for s in self.order
                if s in self.by_stamp and {'depth', 'confidence', 'camera_info'} <= self.by_stamp[s].topics]


# --------------------------------------------------------------------------------------------------------------
# ROS environment
# --------------------------------------------------------------------------------------------------------------
def private_ros_env(out: pathlib.Path, domain_id: Optional[int]) -> Dict[str, str]:
    """Set (in os.environ, before rclpy starts) a DDS domain of our own, localhost-only discovery and ROS_LOG_DIR
    under OUT/logs/ros; the node process inherits them. Returns what was set."""
    if domain_id is None:
        taken = os.environ.get('ROS_DOMAIN_ID')
        rng = random.Random(os.getpid() ^ time.time_ns())
        domain_id = rng.randint(1, 101)
        while str(domain_id) == taken:
            domain_id = rng.randint(1, 101)
    env = {'ROS_DOMAIN_ID': str(int(domain_id)), 'ROS_LOG_DIR': str((out / 'logs' / 'ros').resolve())}
    if 'ROS_LOCALHOST_ONLY' not in os.environ and 'ROS_AUTOMATIC_DISCOVERY_RANGE' not in os.environ:
        env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    os.environ.update(env)
    pathlib.Path(env['ROS_LOG_DIR']).mkdir(parents=True, exist_ok=True)
    return env
