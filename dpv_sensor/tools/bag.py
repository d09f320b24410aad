"""`ros2 run dpv_sensor bag`: write, play, record and export rosbag2 files for dpv_sensor.

  bag write SEQUENCE_DIR OUT_BAG     a sequence folder (or --synthetic SEED) -> rosbag2 with image, camera_info and
                                     odometry (--rate, --odom-rate, --odom-noise, --odom-dropout, --format)
  bag play BAG                       replay into the live ROS graph at real time (or --rate x), with the recorded
                                     QoS, after waiting for subscribers (--wait-for, --wait-timeout); topics are
                                     remapped the ROS way: bag play BAG --ros-args -r /camera/image:=/cam/image
  bag record OUT_BAG [TOPIC ...]     subscribe and write a bag until Ctrl-C or --duration
  bag export BAG OUT_DIR             a recorded depth/confidence bag -> depth PNG (mm) + confidence PNG folder

The file side (reading, writing, export) is dpv_sensor.data.rosbag_io (rosbags library, no rclpy); playing and
recording need a live graph and use rclpy here. `BagPlayer` and `BagRecorder` can be used in-process (tests, the
soak tool) with a node of the caller's own context.
"""
from __future__ import annotations

import argparse
import pathlib
import sys
import threading
import time
from dataclasses import dataclass, field

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
    loops without time going backwards). loop: play again from the start (with rebase_stamps, time keeps increasing across loops).
    """

    def __init__(self, node, bag_path, *, rate: float = 1.0, topics=None, remap=None,
                 rebase_stamps: bool = False, loop: bool = False, reliability: str | None = None,
                 qos_depth: int | None = None):
        from dpv_sensor.msgs import ros_message_class
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
        self.publishers = {t: node.create_publisher(self.classes[t], self.remap.get(t, t),
                                                    qos_from_bag(qos.get(t), reliability, qos_depth))
                           for t in self.topics}
        self.stop_event = threading.Event()
        self.on_publish = None   # optional callback(topic, msg_or_None, bag_stamp_ns, published_stamp_ns)

    @property
    def total_messages(self) -> int:
        return sum(self.counts.values())

    def published_topic(self, bag_topic: str) -> str:
        return self.publishers[bag_topic].topic_name

    def wait_for_subscribers(self, topics=None, timeout: float = 10.0, spin=None, min_count: int = 1) -> list[str]:
        """Wait until every topic in `topics` (bag names; default: all) has at least `min_count` matched
        subscriptions, at most `timeout` s. Returns the topics still short of that (empty list: all matched)."""
        wanted = list(topics) if topics else list(self.topics)
        deadline = time.monotonic() + timeout
        while True:
            missing = [t for t in wanted if self.publishers[t].get_subscription_count() < min_count]
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
        from rclpy.serialization import deserialize_message
        from dpv_sensor.msgs import make_header, stamp_to_ns
        stats = PlaybackStats(per_topic={t: 0 for t in self.topics})
        bar = None
        if progress:
            from tqdm import tqdm
            bar = tqdm(total=None if self.loop else self.total_messages, unit='msg', desc=f'playing {self.path.name}')
        t_start = time.monotonic()
        wall_deadline = None if duration is None else t_start + duration
        try:
            while True:
                loop_start_mono = time.monotonic()
                loop_start_wall = time.time_ns()
                first_log = None
                first_stamp = None
                for topic, _type, log_ns, raw in R.read_messages(self.path, self.topics, raw=True):
                    if first_log is None:
                        first_log = log_ns
                    due = loop_start_mono + (log_ns - first_log) / NS / self.rate
                    while True:
                        now = time.monotonic()
                        if self.stop_event.is_set() or (wall_deadline is not None and now >= wall_deadline) \
                                or not self.node.context.ok():          # Ctrl-C shut the context down
                            stats.stopped = True
                            return stats
                        if now >= due:
                            break
                        time.sleep(min(due - now, 0.05))
                    stats.late_ms_max = max(stats.late_ms_max, (time.monotonic() - due) * 1000.0)
                    pub = self.publishers[topic]
                    try:
                        if self.rebase_stamps:
                            msg = deserialize_message(raw, self.classes[topic])
                            if hasattr(msg, 'header'):
                                old = stamp_to_ns(msg.header.stamp)
                                if first_stamp is None:
                                    first_stamp = old
                                new = loop_start_wall + int((old - first_stamp) / self.rate)
                                msg.header = make_header(new, msg.header.frame_id)
                                if self.on_publish is not None:
                                    self.on_publish(topic, msg, old, new)
                            pub.publish(msg)
                        else:
                            pub.publish(raw)
                            if self.on_publish is not None:
                                self.on_publish(topic, None, log_ns, log_ns)
                    except Exception:
                        if not self.node.context.ok():   # shut down while publishing (Ctrl-C)
                            stats.stopped = True
                            return stats
                        raise
                    stats.published += 1
                    stats.per_topic[topic] += 1
                    if bar is not None:
                        bar.update(1)
                stats.loops += 1
                if not self.loop:
                    return stats
        finally:
            stats.wall_s = time.monotonic() - t_start
            if bar is not None:
                bar.close()


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
        from dpv_sensor.msgs import ros_message_class
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
# command line
# --------------------------------------------------------------------------------------------------------------
def _cmd_write(args) -> int:
    if args.synthetic is not None:
        from dpv_sensor.data.synthetic import render_sequence
        w, h = args.size or (320, 240)
        seq = render_sequence(args.synthetic, args.frames or 60, width=w, height=h, lazy=True)
        print(f'synthetic sequence: seed {args.synthetic}, {len(seq)} frames, {w}x{h}')
    else:
        if not args.sequence:
            raise SystemExit('bag write: give a sequence folder or --synthetic SEED')
        from dpv_sensor.data.sequence import Sequence
        seq = Sequence(args.sequence)
        if args.size:
            seq = seq.resized(*args.size)
    frames = None
    if args.frames and args.synthetic is None:
        frames = range(min(args.frames, len(seq)))
    T_base_camera = args.T_base_camera
    summary = R.write_sequence_bag(
        args.out, seq, storage=args.format, rate=args.rate, odom_rate=args.odom_rate,
        odom_noise=tuple(args.odom_noise), odom_dropout=args.odom_dropout, seed=args.seed, frames=frames,
        image_topic=args.image_topic, camera_info_topic=args.camera_info_topic, odom_topic=args.odom_topic,
        camera_frame=args.camera_frame, odom_frame=args.odom_frame, base_frame=args.base_frame,
        T_base_camera=T_base_camera, encoding=args.encoding, with_odometry=not args.no_odometry,
        overwrite=args.overwrite, progress=not args.no_progress)
    print(f'wrote {summary.path} ({summary.storage}): {summary.frames} images, {summary.odometry} odometry '
          f'messages ({summary.odometry_dropped} dropped on purpose), {summary.duration_s:.2f} s')
    return 0


def _ros_node(name: str, ros_args):
    import rclpy
    rclpy.init(args=ros_args)
    return rclpy.create_node(name)


def _cmd_play(args, ros_args) -> int:
    import rclpy
    from rclpy.executors import ExternalShutdownException
    node = _ros_node('dpv_bag_player', ros_args)
    try:
        player = BagPlayer(node, args.bag, rate=args.rate, topics=args.topics, rebase_stamps=args.rebase_stamps,
                           loop=args.loop, reliability=args.qos_reliability)
        wait_topics = player.topics if args.wait_for == ['all'] else (args.wait_for or [])
        if wait_topics and args.wait_timeout > 0:
            print(f'waiting up to {args.wait_timeout:g} s for {args.wait_count} subscriber(s) on '
                  f'{", ".join(player.published_topic(t) for t in wait_topics)}', flush=True)
            missing = player.wait_for_subscribers(wait_topics, args.wait_timeout, min_count=args.wait_count)
            if missing:
                print(f'no subscriber on {", ".join(player.published_topic(t) for t in missing)} after '
                      f'{args.wait_timeout:g} s; playing anyway', file=sys.stderr, flush=True)
        if args.delay > 0:
            # DDS discovery is not symmetric: a subscriber may learn about our publishers a moment after we see it,
            # and a volatile subscriber misses what is sent before that.
            time.sleep(args.delay)
        print(f'playing {args.bag} ({player.total_messages} messages) at {args.rate:g}x', flush=True)
        stats = player.play(progress=not args.no_progress, duration=args.duration)
        print(f'published {stats.published} messages in {stats.wall_s:.2f} s '
              f'({stats.loops} complete loop(s); worst lateness {stats.late_ms_max:.1f} ms)', flush=True)
        if args.linger > 0:   # let reliable transport deliver the last messages before the publishers go away
            time.sleep(args.linger)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
    return 0


def _cmd_record(args, ros_args) -> int:
    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    if not args.topics and not args.all:
        raise SystemExit('bag record: name topics to record, or --all')
    node = _ros_node('dpv_bag_recorder', ros_args)
    recorder = BagRecorder(node, args.out, args.topics, all_topics=args.all, storage=args.format,
                           overwrite=args.overwrite)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    t0 = time.monotonic()
    last_poll = 0.0
    warned = False
    try:
        while rclpy.ok():
            now = time.monotonic()
            if args.duration and now - t0 >= args.duration:
                break
            if now - last_poll > 0.5:
                missing = recorder.poll()
                last_poll = now
                if missing and not warned and now - t0 > args.wait_timeout:
                    print(f'still waiting for publishers on {", ".join(missing)}', file=sys.stderr, flush=True)
                    warned = True
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        recorder.close()
        print(f'wrote {args.out}: ' + ', '.join(f'{t}: {n}' for t, n in sorted(recorder.counts.items())), flush=True)
        executor.shutdown()
        node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
    return 0


def _cmd_export(args) -> int:
    summary = R.export_depth_bag(args.bag, args.out, depth_topic=args.depth_topic,
                                 confidence_topic=args.confidence_topic, info_topic=args.camera_info_topic,
                                 image_topic=args.image_topic, odom_topic=args.odom_topic, pose_topic=args.pose_topic,
                                 T_base_camera=args.T_base_camera, progress=not args.no_progress)
    print(f"exported {summary['frames']} frames from {summary['depth_topic']} to {args.out}")
    how = summary['chosen_by']
    for role, key in (('image', 'image_topic'), ('odom', 'odom_topic')):
        if summary[key]:
            print(f'  {role}: {summary[key]} ({how.get(role, "named")})')
    for key in ('without_confidence', 'without_image', 'without_pose'):
        if summary[key]:
            print(f'  {summary[key]} frames {key.replace("_", " ")}')
    return 0


def _size(text: str):
    try:
        w, h = text.lower().split('x')
        return int(w), int(h)
    except ValueError:
        raise argparse.ArgumentTypeError(f'size must be WxH, got {text!r}') from None


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog='bag', description=__doc__.split('\n\n')[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest='command', required=True)

    w = sub.add_parser('write', help='sequence folder (or synthetic scene) -> rosbag2')
    w.add_argument('sequence', nargs='?', help='sequence folder (images/, poses.txt, K.txt[, stamps.txt])')
    w.add_argument('out', help='output bag directory')
    w.add_argument('--synthetic', type=int, metavar='SEED', help='render a synthetic sequence instead')
    w.add_argument('--frames', type=int, help='number of frames (synthetic: to render; folder: the first N)')
    w.add_argument('--size', type=_size, help='resize images to WxH (K scaled)')
    w.add_argument('--rate', type=float, help='camera rate in Hz (default: the sequence stamps)')
    w.add_argument('--odom-rate', type=float, help='odometry rate in Hz (default: one message per image)')
    w.add_argument('--odom-noise', type=float, nargs=2, default=(0.0, 0.0), metavar=('POS_M', 'ROT_DEG'),
                   help='white noise sigma per odometry message: position (m) and rotation (deg)')
    w.add_argument('--odom-dropout', type=float, default=0.0, help='probability of leaving out an odometry message')
    w.add_argument('--no-odometry', action='store_true', help='write no odometry topic')
    w.add_argument('--format', choices=R.STORAGES, default='mcap', help='storage plugin (default mcap)')
    w.add_argument('--seed', type=int, default=0, help='random seed of the odometry noise / dropouts')
    w.add_argument('--encoding', default='rgb8', choices=('rgb8', 'bgr8', 'rgba8', 'bgra8', 'mono8'))
    w.add_argument('--image-topic', default=R.IMAGE_TOPIC)
    w.add_argument('--camera-info-topic', default=R.CAMERA_INFO_TOPIC)
    w.add_argument('--odom-topic', default=R.ODOM_TOPIC)
    w.add_argument('--camera-frame', default='camera_optical_frame')
    w.add_argument('--odom-frame', default='odom')
    w.add_argument('--base-frame', default='base_link')
    w.add_argument('--T-base-camera', type=float, nargs=7, metavar='V',
                   help='camera pose in the base frame: x y z qx qy qz qw (default identity)')
    w.add_argument('--overwrite', action='store_true')
    w.add_argument('--no-progress', action='store_true')

    p = sub.add_parser('play', help='replay a bag into the ROS graph')
    p.add_argument('bag')
    p.add_argument('--rate', type=float, default=1.0, help='playback speed factor (default 1 = real time)')
    p.add_argument('--topics', nargs='+', help='only these bag topics')
    p.add_argument('--wait-for', nargs='+', default=['all'],
                   help="bag topics that need a subscriber before playing starts ('all' = every topic; "
                        "give a subset when some topics have no consumer)")
    p.add_argument('--wait-timeout', type=float, default=10.0, help='seconds to wait for subscribers (0: do not wait)')
    p.add_argument('--wait-count', type=int, default=1, help='subscribers each waited-for topic needs (default 1)')
    p.add_argument('--delay', type=float, default=0.5,
                   help='seconds to wait after the subscribers matched before the first message (default 0.5)')
    p.add_argument('--rebase-stamps', action='store_true', help='shift header stamps so playback starts at now')
    p.add_argument('--loop', action='store_true', help='play again from the start until stopped')
    p.add_argument('--duration', type=float, help='stop after this many seconds')
    p.add_argument('--qos-reliability', choices=('reliable', 'best_effort'),
                   help='override the recorded reliability of every publisher')
    p.add_argument('--linger', type=float, default=1.0, help='seconds to keep the publishers after the last message')
    p.add_argument('--no-progress', action='store_true')

    r = sub.add_parser('record', help='record topics of the live graph into a bag')
    r.add_argument('out')
    r.add_argument('topics', nargs='*')
    r.add_argument('--all', action='store_true', help='record every topic that appears')
    r.add_argument('--duration', type=float, help='stop after this many seconds (default: Ctrl-C)')
    r.add_argument('--format', choices=R.STORAGES, default='mcap')
    r.add_argument('--wait-timeout', type=float, default=10.0, help='warn when a topic has no publisher after this')
    r.add_argument('--overwrite', action='store_true')

    e = sub.add_parser('export', help='recorded depth/confidence bag -> depth + confidence PNG folder')
    e.add_argument('bag')
    e.add_argument('out')
    e.add_argument('--depth-topic', default=R.DEPTH_TOPIC)
    e.add_argument('--confidence-topic', default=R.CONFIDENCE_TOPIC)
    e.add_argument('--camera-info-topic', default=R.DEPTH_INFO_TOPIC)
    e.add_argument('--image-topic', default='auto',
                   help='colour images to export alongside (default: the only Image topic that is not a node output, '
                        'if recorded)')
    e.add_argument('--odom-topic', default='auto',
                   help='odometry for poses.txt (default: the only Odometry topic, if recorded)')
    e.add_argument('--pose-topic', help='PoseStamped topic for poses.txt (instead of odometry)')
    e.add_argument('--T-base-camera', type=float, nargs=7, metavar='V')
    e.add_argument('--no-progress', action='store_true')
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv if argv is None else argv
    from rclpy.utilities import remove_ros_args
    own = remove_ros_args(argv)[1:]
    args = build_parser().parse_args(own)
    try:
        if args.command == 'write':
            return _cmd_write(args)
        if args.command == 'export':
            return _cmd_export(args)
        if args.command == 'play':
            return _cmd_play(args, argv)
        if args.command == 'record':
            return _cmd_record(args, argv)
    except R.BagError as exc:
        print(f'bag {args.command}: {exc}', file=sys.stderr)
        return 1
    return 2


if __name__ == '__main__':
    sys.exit(main())
