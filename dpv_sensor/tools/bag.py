"""`ros2 run dpv_sensor bag`: write, play, record and export rosbag2 files for dpv_sensor.

  bag write SEQUENCE_DIR OUT_BAG     a sequence folder (or --synthetic SEED) -> rosbag2 with image, camera_info and
                                     odometry (--rate, --odom-rate, --odom-noise, --odom-dropout, --format);
                                     --compressed [jpeg|png]: image_transport's CompressedImage on /image/compressed;
                                     with --T-base-camera the odometry is of the base frame, and --tf-static writes
                                     that mount on /tf_static (--camera-link NAME: as a two-link chain)
  bag play BAG                       replay into the live ROS graph at real time (or --rate x), with the recorded
                                     QoS, after waiting for subscribers (--wait-for, --wait-timeout); topics are
                                     remapped the ROS way: bag play BAG --ros-args -r /image:=/cam/image
  bag record OUT_BAG [TOPIC ...]     subscribe and write a bag until Ctrl-C or --duration
  bag export BAG OUT_DIR             a recorded depth/confidence bag -> depth PNG (mm) + confidence PNG folder

The file side is dpv_sensor.data.rosbag_io (reading, writing) and dpv_sensor.data.bag_export (export), with the
rosbags library and no rclpy; playing and recording need a live graph and use rclpy here. `BagPlayer` and
`BagRecorder` (dpv_sensor.client.ros_io) can be used in-process (tests, the soak tool) with a node of the caller's
own context.
"""
from __future__ import annotations

import argparse
import sys
import time

from dpv_sensor.data import rosbag_io as R
from dpv_sensor.data.bag_export import export_depth_bag
from dpv_sensor.client.ros_io import BagPlayer, BagRecorder
from dpv_sensor.ros.compressed_image import CODECS

NS = 1_000_000_000


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
        compressed=args.compressed, jpeg_quality=args.jpeg_quality, tf_static=args.tf_static,
        camera_link=args.camera_link, overwrite=args.overwrite, progress=not args.no_progress)
    what = f"CompressedImage '{summary.image_format}'" if args.compressed else f'Image {args.encoding}'
    print(f'wrote {summary.path} ({summary.storage}): {summary.frames} images ({what} on {summary.image_topic}), '
          f'{summary.odometry} odometry messages ({summary.odometry_dropped} dropped on purpose), '
          f'{summary.duration_s:.2f} s')
    if args.tf_static:
        chain = ' -> '.join(f for f in (args.base_frame, args.camera_link, args.camera_frame) if f)
        print(f'camera mount on {R.TF_STATIC_TOPIC}: {chain}')
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
        executor = rclpy.executors.SingleThreadedExecutor(context=node.context)
        executor.add_node(node)     # delivers the publishers' matched events while waiting for subscribers
        wait_topics = player.topics if args.wait_for == ['all'] else (args.wait_for or [])
        if wait_topics and args.wait_timeout > 0:
            print(f'waiting up to {args.wait_timeout:g} s for {args.wait_count} subscriber(s) on '
                  f'{", ".join(player.published_topic(t) for t in wait_topics)}', flush=True)
            missing = player.wait_for_subscribers(wait_topics, args.wait_timeout, min_count=args.wait_count,
                                                  spin=lambda t: executor.spin_once(timeout_sec=t))
            if missing:
                print(f'no subscriber on {", ".join(player.published_topic(t) for t in missing)} after '
                      f'{args.wait_timeout:g} s; playing anyway', file=sys.stderr, flush=True)
        if args.delay > 0:
            # Optional pause after the subscriptions matched, for consumers that need time to set up after
            # subscribing (waiting for matched subscriptions already covers DDS discovery).
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
    summary = export_depth_bag(args.bag, args.out, depth_topic=args.depth_topic,
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
    w.add_argument('--compressed', nargs='?', const='jpeg', choices=CODECS, default=None,
                   help="write image_transport's sensor_msgs/CompressedImage (JPEG, or --compressed png) instead "
                        'of sensor_msgs/Image, as robots record a camera (the node reads it with '
                        'image_transport=compressed)')
    w.add_argument('--jpeg-quality', type=int, default=90, help='JPEG quality 1-100 with --compressed (default 90)')
    w.add_argument('--image-topic', default=None,
                   help=f'image topic (default {R.IMAGE_TOPIC}; {R.IMAGE_TOPIC}{R.COMPRESSED_SUFFIX} with '
                        '--compressed)')
    w.add_argument('--camera-info-topic', default=R.CAMERA_INFO_TOPIC)
    w.add_argument('--odom-topic', default=R.ODOM_TOPIC)
    w.add_argument('--camera-frame', default='camera_optical_frame')
    w.add_argument('--odom-frame', default='odom')
    w.add_argument('--base-frame', default='base_link')
    w.add_argument('--T-base-camera', type=float, nargs=7, metavar='V',
                   help='camera pose in the base frame: x y z qx qy qz qw (default identity); the odometry is of '
                        'the base frame: T_world_base = T_world_cam @ inv(T_base_camera)')
    w.add_argument('--tf-static', action='store_true',
                   help='also write the camera mount on /tf_static (latched), as a URDF publishes it: the node then '
                        'needs no T_base_camera')
    w.add_argument('--camera-link', default='',
                   help='with --tf-static: write the mount as base frame -> CAMERA_LINK (translation) -> camera frame '
                        '(rotation), e.g. camera_link'),
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
    p.add_argument('--delay', type=float, default=0.0,
                   help='extra seconds to wait after the subscribers matched, before the first message (default 0)')
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
                        'else the only image_transport CompressedImage topic, if recorded)')
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
