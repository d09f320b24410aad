"""Does a camera stream arrive complete over DDS on one machine? Figures per transport configuration.

    .venv/bin/python -m dpv_sensor.benchmarks.transport [--seconds 10] [--configs default,node ...]

Each configuration runs two processes on the ROS graph: a *sensor* process (``publish``: 640x480 rgb8 images and
camera_info at 30 Hz, nav_msgs/Odometry at 100 Hz, with a chosen reliability; it sets no transport of its own
unless the configuration says so, like a user's camera driver) and a *receiver* process (``receive``: plain
subscriptions that count what arrives and how late). The receiver either keeps the Fast DDS defaults or applies the
node's own transport settings (:func:`dpv_sensor.ros.transport.configure`). The table printed at the end gives, per
topic, messages received / sent and the arrival delay after the header stamp (median, max in ms).

The two roles are also usable alone (the transport acceptance test uses ``publish``):

    python -m dpv_sensor.benchmarks.transport publish --reliability best_effort --seconds 10 --wait-subscribers 1
    python -m dpv_sensor.benchmarks.transport receive --reliability reliable --depth 10 --node-transport
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import threading
import time

WIDTH, HEIGHT = 640, 480
IMAGE_HZ, ODOM_HZ = 30.0, 100.0
TOPICS = ('image', 'camera_info', 'odom')
NS = 1_000_000_000


def _qos(reliability: str, depth: int):
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    rel = {'best_effort': ReliabilityPolicy.BEST_EFFORT, 'reliable': ReliabilityPolicy.RELIABLE}[reliability]
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=rel,
                      durability=DurabilityPolicy.VOLATILE)


# ---------------------------------------------------------------------------------------------------- publisher
def publish(reliability: str = 'best_effort', seconds: float = 10.0, depth: int = 5, wait_subscribers: int = 1,
            wait_timeout: float = 60.0, prefix: str = '', width: int = WIDTH, height: int = HEIGHT,
            wait_go: bool = False) -> dict:
    """Publish `seconds` of camera (image + camera_info at 30 Hz) and odometry (100 Hz) on `prefix`image,
    `prefix`camera_info, `prefix`odom, once each publisher sees `wait_subscribers` subscriptions. Stamps are the
    wall clock at the scheduled send time, so a receiver sees one image every 1/30 s exactly in stamp time.
    wait_go: after matching, print 'matched' and wait for a line on stdin before sending (a test first checks the
    receiver). Returns {'sent': {topic: n}, 'first_image_ns': .., 'last_image_ns': .., 'late_ms_max': ..}."""
    import numpy as np
    import rclpy
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import CameraInfo, Image

    rclpy.init()
    node = rclpy.create_node('transport_sensor')
    qos = _qos(reliability, depth)
    pubs = {'image': node.create_publisher(Image, prefix + 'image', qos),
            'camera_info': node.create_publisher(CameraInfo, prefix + 'camera_info', qos),
            'odom': node.create_publisher(Odometry, prefix + 'odom', qos)}
    deadline = time.monotonic() + wait_timeout
    while time.monotonic() < deadline and any(p.get_subscription_count() < wait_subscribers for p in pubs.values()):
        rclpy.spin_once(node, timeout_sec=0.05)
    matched = {k: p.get_subscription_count() for k, p in pubs.items()}
    if wait_go:
        print('matched', flush=True)
        sys.stdin.readline()
    time.sleep(1.0)   # let the other side match our writers as well (discovery is not symmetric in time)

    # one image (a gradient with a moving bar), reused with new stamps: building it costs more than sending it
    img = Image(height=height, width=width, encoding='rgb8', is_bigendian=0, step=3 * width)
    pixels = np.zeros((height, width, 3), np.uint8)
    pixels[..., 0] = np.linspace(0, 255, width, dtype=np.uint8)[None, :]
    pixels[..., 1] = np.linspace(0, 255, height, dtype=np.uint8)[:, None]
    img.data = pixels.tobytes()
    img.header.frame_id = 'camera'
    info = CameraInfo(width=width, height=height, distortion_model='plumb_bob')
    info.header.frame_id = 'camera'
    info.k = [0.8 * width, 0.0, width / 2, 0.0, 0.8 * width, height / 2, 0.0, 0.0, 1.0]
    info.p = [0.8 * width, 0.0, width / 2, 0.0, 0.0, 0.8 * width, height / 2, 0.0, 0.0, 0.0, 1.0, 0.0]
    info.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    info.d = [0.0] * 5
    odom = Odometry()
    odom.header.frame_id = 'odom'
    odom.child_frame_id = 'base_link'
    odom.pose.pose.orientation.w = 1.0

    def stamp(msg, ns):
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(ns, NS)

    sent = {k: 0 for k in TOPICS}
    image_period, odom_period = NS / IMAGE_HZ, NS / ODOM_HZ
    t0 = (time.time_ns() // NS + 1) * NS
    n_images, n_odom = int(seconds * IMAGE_HZ), int(seconds * ODOM_HZ) + 4   # odometry runs past the last image
    events = sorted([(int(round(t0 + i * odom_period)), 0, i) for i in range(n_odom)]
                    + [(int(round(t0 + i * image_period)), 1, i) for i in range(n_images)])
    late_max = 0.0
    for t_ns, kind, i in events:
        wait = (t_ns - time.time_ns()) / NS
        if wait > 0:
            time.sleep(wait)
        late_max = max(late_max, (time.time_ns() - t_ns) / 1e6)
        if kind == 0:
            stamp(odom, t_ns)
            odom.pose.pose.position.x = 0.001 * i     # 0.1 m/s
            pubs['odom'].publish(odom)
            sent['odom'] += 1
        else:
            stamp(info, t_ns)
            stamp(img, t_ns)
            pubs['camera_info'].publish(info)
            pubs['image'].publish(img)
            sent['camera_info'] += 1
            sent['image'] += 1
    # reliable writers keep resending what a reader lacks: give them a moment before the process goes away
    end = time.monotonic() + 2.0
    while time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.1)
    node.destroy_node()
    rclpy.shutdown()
    return {'sent': sent, 'matched': matched, 'first_image_ns': t0,
            'last_image_ns': int(round(t0 + (n_images - 1) * image_period)), 'late_ms_max': round(late_max, 1)}


# ---------------------------------------------------------------------------------------------------- receiver
def receive(reliability: str = 'best_effort', depth: int = 5, prefix: str = '', stop_file: str | None = None) -> dict:
    """Count what arrives on the three topics until SIGINT/SIGTERM (or until `stop_file` exists); returns per topic
    {'received', 'delay_ms_median', 'delay_ms_max'} (delay = receipt wall time - header stamp)."""
    import rclpy
    from nav_msgs.msg import Odometry
    from rclpy.signals import SignalHandlerOptions
    from sensor_msgs.msg import CameraInfo, Image

    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node('transport_receiver')
    delays: dict[str, list[float]] = {k: [] for k in TOPICS}

    def on(topic):
        def callback(msg):
            st = msg.header.stamp
            delays[topic].append((time.time_ns() - (st.sec * NS + st.nanosec)) / 1e6)
        return callback

    qos = _qos(reliability, depth)
    subs = [node.create_subscription(Image, prefix + 'image', on('image'), qos),
            node.create_subscription(CameraInfo, prefix + 'camera_info', on('camera_info'), qos),
            node.create_subscription(Odometry, prefix + 'odom', on('odom'), qos)]
    print('receiver ready', flush=True)
    while not stop.is_set() and not (stop_file and os.path.exists(stop_file)):
        rclpy.spin_once(node, timeout_sec=0.05)
    del subs
    node.destroy_node()
    rclpy.shutdown()
    out = {}
    for k, d in delays.items():
        d = sorted(d)
        out[k] = {'received': len(d), 'delay_ms_median': round(d[len(d) // 2], 1) if d else None,
                  'delay_ms_max': round(d[-1], 1) if d else None}
    return out


# ---------------------------------------------------------------------------------------------------- driver
# name -> (receiver applies the node's transport settings, environment of both processes)
CONFIGS = {
    'default': (False, {}),
    'udp': (False, {'FASTDDS_BUILTIN_TRANSPORTS': 'UDPv4'}),
    'shm': (False, {'FASTDDS_BUILTIN_TRANSPORTS': 'SHM'}),
    'large_data': (False, {'FASTDDS_BUILTIN_TRANSPORTS': 'LARGE_DATA'}),
    'node': (True, {}),
    # the node's profile set by hand (in the subnet discovery range it is what configure() applies)
    'profile': (False, {'FASTRTPS_DEFAULT_PROFILES_FILE': 'config/fastdds.xml'}),
    # a variant: shared memory with a 16 MiB segment next to the same UDP transport (the file is written at run time)
    'shm16m_udp': (False, {'FASTRTPS_DEFAULT_PROFILES_FILE': '<shm16m_udp>'}),
}
SHM16M_UDP = """<?xml version="1.0" encoding="UTF-8"?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <transport_descriptors>
    <transport_descriptor><transport_id>shm</transport_id><type>SHM</type>
      <segment_size>16777216</segment_size></transport_descriptor>
    <transport_descriptor><transport_id>udp</transport_id><type>UDPv4</type>
      <sendBufferSize>4194304</sendBufferSize><receiveBufferSize>4194304</receiveBufferSize></transport_descriptor>
  </transport_descriptors>
  <participant profile_name="shm16m_udp" is_default_profile="true"><rtps>
    <userTransports><transport_id>shm</transport_id><transport_id>udp</transport_id></userTransports>
    <useBuiltinTransports>false</useBuiltinTransports>
  </rtps></participant>
</profiles>
"""
TRANSPORT_VARS = ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE', 'FASTDDS_BUILTIN_TRANSPORTS',
                  'RMW_FASTRTPS_USE_QOS_FROM_XML')


def _clean_env(extra: dict) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in TRANSPORT_VARS}
    env.update(extra)
    if env.get('FASTRTPS_DEFAULT_PROFILES_FILE') == '<shm16m_udp>':
        import tempfile
        path = os.path.join(tempfile.gettempdir(), f'dpv_sensor_shm16m_udp_{os.getpid()}.xml')
        with open(path, 'w') as f:
            f.write(SHM16M_UDP)
        env['FASTRTPS_DEFAULT_PROFILES_FILE'] = path
    env.setdefault('PYTHONUNBUFFERED', '1')
    return env


def run_config(name: str, reliability: str, seconds: float, depth: int, sensor_env: str = 'default') -> dict:
    """One run: receiver (config `name`) + sensor (config `sensor_env`, 'default' = no transport settings)."""
    node_transport, env = CONFIGS[name]
    recv_cmd = [sys.executable, '-m', 'dpv_sensor.benchmarks.transport', 'receive', '--reliability', reliability,
                '--depth', str(depth)] + (['--node-transport'] if node_transport else [])
    pub_cmd = [sys.executable, '-m', 'dpv_sensor.benchmarks.transport', 'publish', '--reliability', reliability,
               '--seconds', str(seconds), '--depth', str(depth)]
    recv = subprocess.Popen(recv_cmd, env=_clean_env(env), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert recv.stdout.readline().strip() == 'receiver ready', recv.communicate()
        pub = subprocess.run(pub_cmd, env=_clean_env(CONFIGS[sensor_env][1]), capture_output=True, text=True,
                             timeout=seconds + 120)
        time.sleep(3.0)    # stragglers (reliable repairs)
    finally:
        recv.send_signal(signal.SIGINT)
        out, err = recv.communicate(timeout=30)
    if pub.returncode != 0:
        raise RuntimeError(f'publisher failed: {pub.stderr[-2000:]}')
    got = json.loads(out.strip().splitlines()[-1])
    sent = json.loads(pub.stdout.strip().splitlines()[-1])
    return {'config': name, 'sensor': sensor_env, 'reliability': reliability, 'depth': depth, 'sent': sent['sent'],
            'matched': sent['matched'], 'publisher_late_ms_max': sent['late_ms_max'], 'received': got}


def _row(r: dict) -> str:
    cells = []
    for k in TOPICS:
        g = r['received'][k]
        cells.append(f"{g['received']:4d}/{r['sent'][k]:<4d} {g['delay_ms_median'] or 0:7.1f} "
                     f"{g['delay_ms_max'] or 0:8.1f}")
    return f"{r['config']:<11} {r['sensor']:<9}{r['reliability']:<12}{r['depth']:>3}  " + '  '.join(cells)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    sub = ap.add_subparsers(dest='role')
    p = sub.add_parser('publish', help='the sensor process')
    p.add_argument('--reliability', choices=('best_effort', 'reliable'), default='best_effort')
    p.add_argument('--seconds', type=float, default=10.0)
    p.add_argument('--depth', type=int, default=5)
    p.add_argument('--wait-subscribers', type=int, default=1)
    p.add_argument('--prefix', default='')
    p.add_argument('--wait-go', action='store_true', help="print 'matched', then wait for a line on stdin")
    p.add_argument('--node-transport', action='store_true', help="apply the node's transport settings first")
    r = sub.add_parser('receive', help='the counting receiver process')
    r.add_argument('--reliability', choices=('best_effort', 'reliable'), default='best_effort')
    r.add_argument('--depth', type=int, default=5)
    r.add_argument('--prefix', default='')
    r.add_argument('--node-transport', action='store_true', help="apply the node's transport settings first")
    ap.add_argument('--seconds', type=float, default=10.0)
    ap.add_argument('--depth', type=int, default=5)
    ap.add_argument('--configs', default='default,udp,large_data,shm16m_udp,profile,node',
                    help=f'receiver configurations, from {",".join(CONFIGS)}')
    ap.add_argument('--sensor', default='default', help='configuration of the sensor process (default: none)')
    ap.add_argument('--reliability', default='best_effort,reliable')
    ap.add_argument('--json', help='write all results here')
    args = ap.parse_args(argv)
    if args.role == 'publish':
        if args.node_transport:
            from dpv_sensor.ros.transport import configure
            configure()
        print(json.dumps(publish(args.reliability, args.seconds, args.depth, args.wait_subscribers,
                                 prefix=args.prefix, wait_go=args.wait_go)), flush=True)
        return 0
    if args.role == 'receive':
        if args.node_transport:
            from dpv_sensor.ros.transport import configure
            configure()
        print(json.dumps(receive(args.reliability, args.depth, args.prefix)), flush=True)
        return 0
    results = []
    print(f"{'receiver':<11} {'sensor':<9}{'reliability':<12}{'dep':>3}  "
          + '  '.join(f'{k + " recv/sent p50ms maxms":<27}' for k in TOPICS), flush=True)
    for name in args.configs.split(','):
        for rel in args.reliability.split(','):
            res = run_config(name, rel, args.seconds, args.depth, args.sensor)
            results.append(res)
            print(_row(res), flush=True)
    if args.json:
        with open(args.json, 'w') as f:
            json.dump(results, f, indent=1)
    return 0


if __name__ == '__main__':
    sys.exit(main())
