"""The node's RGB-D outputs over real DDS: a rendered bag replayed into two node processes.

Node A (output_resolution input, publish_compressed_depth) and node B (namespace /pr: output_resolution processing
with processing 96x64 from 160x128 input, i.e. 96x77 out with the input's aspect ratio; a distorted camera_info of
its own, so it rectifies; points with points_decimation 2 and points_max_rate 3 Hz; expected_depth_rate 50 Hz).
Checked, for every output of each node:
- rgb/image, rgb/camera_info, depth/image, confidence/image, confidence/camera_info pair by exact stamp, with the
  image's frame_id, the same size, the same K (D zero);
- the colour pixels equal the bag's image of that stamp: as it is (A), rectified then resized with INTER_AREA to the
  output size (B);
- A's compressedDepth decodes to its depth/image (32FC1 inverse-depth code: within its quantisation);
- B's clouds are the decimated grid and no two are closer than 1/points_max_rate in image time, the skipped ones
  counted in /diagnostics; B's /diagnostics warns that depth/image is below its expected rate, A's never does (B
  judges its rate once images have come for a whole rate_window of wall time: it hears slow images after the replay
  until it has, so the check waits on that condition, not on the replay's timing under load).
A second test: /diagnostics warns once more than drop_warn_share of the recent images are rejected as faulty.
"""
import threading
import time

import cv2
import numpy as np
import pytest

from ros_helpers import assert_clean_exits, start_node, stop_all, stop_process, wait_for, write_rendered_bag
from test_node_integration import COMMON, T_BASE_CAMERA, ros_args
from dpv_sensor.ros import msgs as M
from dpv_sensor.ros import pose_msgs as PM
from dpv_sensor.ros import compressed_depth as CD
from dpv_sensor.data import rosbag_io as R
from dpv_sensor.core.rectify import RectifierCache
from dpv_sensor.client.ros_io import BagPlayer

W, H = 160, 128
FRAMES = 24
START_NS = 1_700_000_000_123_456_789
PW, PH = 96, 64                    # processing size of node B (aspect 1.5, the input's 1.25)
OUT_B = (96, 77)                   # processing_width wide with the input's aspect: round(96 * 128 / 160) = 77
POINTS_RATE = 3.0
DISTORTION = [-0.12, 0.03, 0.001, -0.002, 0.0]
OUTPUT_TOPICS = {'depth': 'depth/image', 'depth_info': 'depth/camera_info', 'rgb': 'rgb/image',
                 'rgb_info': 'rgb/camera_info', 'conf': 'confidence/image', 'conf_info': 'confidence/camera_info'}
WARN = 1
_Y, _X = np.mgrid[0:H, 0:W]
_G = (((_X // 8 + _Y // 8) % 2) * 100 + 60 + _X // 4).astype(np.uint8)
TEXTURE = np.stack([_G, _G, 255 - _G], -1)      # checkerboard on a ramp: an image the node accepts (not degenerate)


@pytest.fixture(scope='module')
def scene(tmp_path_factory):
    return write_rendered_bag(tmp_path_factory, 5, FRAMES, W, H, 'outputs', start_ns=START_NS,
                              T_base_camera=T_BASE_CAMERA)


class Outputs:
    """Every output topic of one node under `ns`, grouped by header stamp, and its /diagnostics history."""

    def __init__(self, node, ns: str, diag_name: str, extra=()):
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.event_handler import SubscriptionEventCallbacks
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        self.by_stamp: dict[int, dict] = {}
        # DDS-matched publishers per output kind: the graph lists a publisher before its writer has matched this
        # reader, and a reliable volatile writer drops what it publishes before the match
        self.matched: dict[str, int] = {}
        self.diag_history: list[tuple[int, str]] = []
        self.diag_count = 0
        self.diagnostics: dict = {}
        self.lock = threading.Lock()
        types = {'depth': Image, 'rgb': Image, 'conf': Image, 'points': PointCloud2, 'compressed': CompressedImage}
        topics = dict(OUTPUT_TOPICS, points='depth/points', compressed='depth/image/compressedDepth')
        self.subs = {}
        self.topics = {kind: topics[kind] for kind in list(OUTPUT_TOPICS) + list(extra)}
        for kind in list(OUTPUT_TOPICS) + list(extra):
            events = SubscriptionEventCallbacks(
                matched=lambda info, kind=kind: self.matched.update({kind: info.current_count}))
            self.subs[kind] = node.create_subscription(types.get(kind, CameraInfo), f'{ns}/{topics[kind]}',
                                                       lambda m, kind=kind: self._on(kind, m), qos,
                                                       event_callbacks=events)
        self.diag_name = diag_name
        node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, qos)

    def _on(self, kind, msg):
        with self.lock:
            self.by_stamp.setdefault(M.stamp_to_ns(msg.header.stamp), {})[kind] = msg

    def _on_diag(self, msg):
        for st in msg.status:
            if st.name == self.diag_name:
                level = int.from_bytes(st.level, 'little') if isinstance(st.level, bytes) else int(st.level)
                self.diag_history.append((level, st.message))
                self.diagnostics = {kv.key: kv.value for kv in st.values}
                self.diag_count += 1

    def diag_int(self, key):
        try:
            return int(self.diagnostics.get(key, -1))
        except ValueError:
            return -1

    def complete(self):
        with self.lock:
            return {s: d for s, d in self.by_stamp.items() if set(OUTPUT_TOPICS) <= set(d)}

    def all_matched(self) -> bool:
        """Each output subscription here has matched the node's publisher, and the node's writer has matched it
        (its /diagnostics says so): DDS matches the two sides apart, and a reliable volatile writer sends nothing
        to a reader it has not matched yet."""
        return all(self.matched.get(kind, 0) == 1 and self.diag_int(f'subscribers.{topic}') == 1
                   for kind, topic in self.topics.items())

    def missing(self) -> dict:
        """For each stamp not complete (ms after the bag's start): the output kinds that have not come."""
        with self.lock:
            return {(s - START_NS) // 1_000_000: sorted(set(OUTPUT_TOPICS) - set(d)) for s, d in self.by_stamp.items()
                    if not set(OUTPUT_TOPICS) <= set(d)}


def _distorted_info(seq):
    info = M.K_to_camera_info(seq.K, W, H, M.make_header(START_NS, 'cam_optical'))
    info.d = list(DISTORTION)
    return info


def _check_pairing(recs, frame_id, size, K_expected):
    """The five image/camera_info outputs of one stamp agree: header, size, K, D zero."""
    w, h = size
    for stamp, d in recs.items():
        for kind in OUTPUT_TOPICS:
            assert M.stamp_to_ns(d[kind].header.stamp) == stamp and d[kind].header.frame_id == frame_id, kind
            assert (d[kind].width, d[kind].height) == (w, h), (kind, d[kind].width, d[kind].height)
        assert d['rgb'].encoding == 'rgb8'
        for kind in ('depth_info', 'rgb_info', 'conf_info'):
            np.testing.assert_allclose(M.camera_info_to_K(d[kind])[0], K_expected, rtol=1e-9, atol=1e-9)
            assert not np.any(np.asarray(d[kind].d)), kind
        assert list(d['rgb_info'].k) == list(d['depth_info'].k) == list(d['conf_info'].k)


def _wait_rate_warning(node, b, seq, summary, spin, timeout=60.0):
    """Node B's rate warnings: those of the replay, else after more images (one every 0.2 s of wall time, stamps
    going on after the bag's, the camera standing at its last pose) until it has judged its rate."""
    from nav_msgs.msg import Odometry
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image
    from dpv_sensor.stream.pose_buffer import pose7_to_matrix

    def warned():
        return [(lvl, m) for lvl, m in list(b.diag_history) if 'depth/image at' in m]
    if warned():
        return warned()
    qos = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
    pub_img = node.create_publisher(Image, R.IMAGE_TOPIC, qos)
    pub_odom = node.create_publisher(Odometry, R.ODOM_TOPIC, qos)
    T_world_base = seq.pose(len(seq) - 1) @ np.linalg.inv(pose7_to_matrix(T_BASE_CAMERA))
    stamp = summary.image_stamps_ns[-1]
    deadline = time.monotonic() + timeout
    while not warned() and time.monotonic() < deadline:
        stamp += 1_000_000_000 // 30
        pub_odom.publish(PM.matrix_to_odometry(T_world_base, stamp, 'base_link', 'odom'))
        pub_img.publish(M.rgb_to_image(seq.image(len(seq) - 1), stamp, 'cam_optical'))
        wait_for(lambda: False, timeout=0.2, spin=spin)      # pacing of the slow stream, not a condition
    return warned()


def test_rgb_confidence_info_compressed_points_and_rate_warning_in_both_resolutions(scene, observer):
    from sensor_msgs.msg import CameraInfo
    seq, bag, summary = scene
    node, executor = observer
    info_pub = node.create_publisher(CameraInfo, '/distorted/camera_info', 10)
    distorted = _distorted_info(seq)

    def spin(t):      # node B's camera_info comes from here, not from the bag: keep sending it
        info_pub.publish(distorted)
        executor.spin_once(timeout_sec=t)

    a = Outputs(node, '', 'dpv_sensor: depth camera', extra=('compressed',))
    b = Outputs(node, '/pr', 'pr/dpv_sensor: depth camera', extra=('points',))
    common = {**COMMON, 'processing_width': 80, 'processing_height': 64, 'T_base_camera': T_BASE_CAMERA,
              'keyframe_max_interval': 2}
    env = {'OMP_NUM_THREADS': '1'}
    proc_a = start_node(ros_args({**common, 'publish_compressed_depth': True, 'use_sim_time': True}), env=env)
    args_b = ros_args({**common, 'processing_width': PW, 'processing_height': PH, 'output_resolution': 'processing',
                       'points_decimation': 2, 'points_max_rate': POINTS_RATE, 'expected_depth_rate': 50.0,
                       'rate_window': 2.0}, ['-r', '__ns:=/pr'])
    # the first remap rule of a name wins: node B's camera_info is the distorted one published here
    args_b[args_b.index('camera_info:=/camera_info')] = 'camera_info:=/distorted/camera_info'
    proc_b = start_node(args_b, env=env)
    player = BagPlayer(node, bag, rate=0.25)
    # node A runs on sim time: /clock follows the bag's stamps
    from rosgraph_msgs.msg import Clock
    clock_pub = node.create_publisher(Clock, '/clock', 10)

    def on_publish(_topic, _msg, bag_stamp_ns, _stamp_ns):
        clock_pub.publish(Clock(clock=M.ns_to_stamp(bag_stamp_ns)))
    player.on_publish = on_publish
    played = {}
    try:
        ready = wait_for(lambda: all(o.diagnostics.get('measurement_model') == 'classical'
                                     and o.diag_int('publishers.image') == 1 and o.diag_int('publishers.odom') == 1
                                     and o.diag_int('publishers.camera_info') >= 1 for o in (a, b))
                         and all(o.all_matched() for o in (a, b)),
                         timeout=90.0, spin=spin)
        assert proc_a.poll() is None and proc_b.poll() is None, 'a node exited early'
        assert ready, (f'the nodes never got ready: matched A {a.matched} B {b.matched}\n'
                       f'A {a.diagnostics}\nB {b.diagnostics}')
        assert not player.wait_for_subscribers([R.IMAGE_TOPIC, R.ODOM_TOPIC], min_count=2, timeout=10.0, spin=spin)
        assert not player.wait_for_subscribers([R.CAMERA_INFO_TOPIC], min_count=1, timeout=10.0, spin=spin)
        assert wait_for(lambda: b.diagnostics.get('rectification', '').startswith('on'), timeout=20.0, spin=spin), \
            b.diagnostics
        thread = threading.Thread(target=lambda: played.update(stats=player.play()), daemon=True)
        thread.start()
        done = wait_for(lambda: not thread.is_alive()
                        and all(o.diag_int('frames_processed') + o.diag_int('dropped_total') == FRAMES
                                and o.diag_int('outputs_published') == len(o.complete()) for o in (a, b)),
                        timeout=120.0, spin=spin)
        assert done, (f'replay did not finish: player running {thread.is_alive()}; ' + '; '.join(
            f"{n}: processed {o.diag_int('frames_processed')} + dropped {o.diag_int('dropped_total')} of {FRAMES}, "
            f"published {o.diag_int('outputs_published')}, received complete {len(o.complete())} of "
            f"{len(o.by_stamp)} stamps, missing (ms after the first image: kinds) {o.missing()}"
            for n, o in (('A', a), ('B', b)))
            + f'\nA {a.diagnostics}\nB {b.diagnostics}')
        # the last diagnostics of the run (two more ticks of each node) and every cloud node B counted
        ticks = (a.diag_count, b.diag_count)
        settled = wait_for(lambda: a.diag_count >= ticks[0] + 2 and b.diag_count >= ticks[1] + 2 and
                           len([1 for d in list(b.by_stamp.values()) if 'points' in d]) ==
                           b.diag_int('point_clouds_published'), timeout=30.0, spin=spin)
        assert settled, b.diagnostics
        snapshot_a, by_stamp_a, history_a = dict(a.diagnostics), dict(a.by_stamp), list(a.diag_history)
        snapshot_b, by_stamp_b = dict(b.diagnostics), dict(b.by_stamp)
        # node B judges its rate once images have arrived for a whole rate_window (wall clock): on a loaded machine
        # the replay's images can reach it within less than that, so it hears slow images until it has judged
        warned = _wait_rate_warning(node, b, seq, summary, spin)
    finally:
        exits = stop_all(proc_a, proc_b)
        player.stop()
    assert_clean_exits(exits)
    index = {s: i for i, s in enumerate(summary.image_stamps_ns)}

    # ---------------- node A: input resolution, the bag's colour image exactly
    recs_a = {s: d for s, d in by_stamp_a.items() if set(OUTPUT_TOPICS) <= set(d)}
    assert len(recs_a) >= 4 and len(recs_a) == len(by_stamp_a), (len(recs_a), len(by_stamp_a))
    _check_pairing(recs_a, 'cam_optical', (W, H), seq.K)
    for stamp, d in recs_a.items():
        np.testing.assert_array_equal(M.image_to_rgb(d['rgb']), seq.image(index[stamp]))
        depth = M.image_to_float(d['depth'])
        decoded = CD.compressed_depth_to_float(d['compressed'])
        assert d['compressed'].format == '32FC1; compressedDepth png'
        np.testing.assert_array_equal(np.isfinite(decoded), np.isfinite(depth) & (depth < 10.0))
        ok = np.isfinite(decoded)
        # inverse-depth code: one step of q = a / d + b is d^2 / a, a = 10100
        assert np.all(np.abs(decoded[ok] - depth[ok]) <= depth[ok] ** 2 / 10100 * 1.01 + 1e-6)
    assert not any('depth/image at' in m for _lvl, m in history_a), history_a
    # stamp age on the node's (sim) clock: within the bag's span (its /clock may lag or lead the images a little
    # under load), not the years since the recording
    age = float(snapshot_a['stamp_age_ms_median'])
    assert abs(age) <= FRAMES / 30 * 1000, age

    # ---------------- node B: processing width with the input's aspect, rectified colour, K of that size
    rect = RectifierCache().for_camera_info(distorted)
    K_b = M.scale_K(rect.K, (W, H), OUT_B)
    recs_b = {s: d for s, d in by_stamp_b.items() if set(OUTPUT_TOPICS) <= set(d)}
    assert len(recs_b) >= 4 and len(recs_b) == len(by_stamp_b), (len(recs_b), len(by_stamp_b))
    _check_pairing(recs_b, 'cam_optical', OUT_B, K_b)
    for stamp, d in recs_b.items():
        expected = cv2.resize(rect.rectify(seq.image(index[stamp])), OUT_B, interpolation=cv2.INTER_AREA)
        assert not np.array_equal(expected, cv2.resize(seq.image(index[stamp]), OUT_B, interpolation=cv2.INTER_AREA))
        np.testing.assert_array_equal(M.image_to_rgb(d['rgb']), expected)
    # points: decimated grid, at most POINTS_RATE per second of image time, the rest counted
    clouds = sorted(s for s, d in by_stamp_b.items() if 'points' in d)
    assert clouds and set(clouds) <= set(recs_b)
    for s in clouds:
        cloud = by_stamp_b[s]['points']
        assert (cloud.width, cloud.height) == ((OUT_B[0] + 1) // 2, (OUT_B[1] + 1) // 2)
    assert all(t1 - t0 >= 1e9 / POINTS_RATE for t0, t1 in zip(clouds, clouds[1:])), np.diff(clouds) / 1e9
    skipped = int(snapshot_b['points_skipped_rate_cap'])
    assert skipped > 0 and skipped + len(clouds) == len(recs_b), (skipped, len(clouds), len(recs_b))
    assert int(snapshot_b['point_clouds_published']) == len(clouds)
    # the keyframe outputs come far below the 50 Hz node B expects: /diagnostics says so
    assert warned and all(lvl >= WARN for lvl, _m in warned), b.diag_history
    assert float(snapshot_b['depth_rate_hz']) < 45.0


def test_diagnostics_warn_when_the_share_of_faulty_images_is_too_high(observer):
    """Images with an unsupported encoding are rejected as faulty: up to drop_warn_share of the recent ones leave
    the level OK, more raise it to WARN (drop_error_share 1: never ERROR here). Images replaced while the node is
    busy (a burst sent at once) are counted in dropped.busy and do not count as faulty."""
    from diagnostic_msgs.msg import DiagnosticArray
    from nav_msgs.msg import Odometry
    from rclpy.event_handler import PublisherEventCallbacks
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import CameraInfo, Image
    node, executor = observer
    spin = lambda t: executor.spin_once(timeout_sec=t)  # noqa: E731
    history = []

    def on_diag(msg):
        for st in msg.status:
            if st.name == 'dpv_sensor: depth camera':
                level = int.from_bytes(st.level, 'little') if isinstance(st.level, bytes) else int(st.level)
                history.append((level, st.message, {kv.key: kv.value for kv in st.values}))
    node.create_subscription(DiagnosticArray, '/diagnostics', on_diag, 10)
    qos = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
    matched = {}     # DDS-matched subscriptions per topic (the graph lists a subscription before it is matched)

    def events(topic):
        return PublisherEventCallbacks(matched=lambda info: matched.update({topic: info.current_count}))
    pub_img = node.create_publisher(Image, '/image', qos, event_callbacks=events('image'))
    pub_info = node.create_publisher(CameraInfo, '/camera_info', qos, event_callbacks=events('info'))
    pub_odom = node.create_publisher(Odometry, '/odom', qos, event_callbacks=events('odom'))
    proc = start_node(ros_args({**COMMON, 'drop_warn_share': 0.3, 'drop_error_share': 1.0, 'rate_window': 30.0}))
    stamp = [START_NS]
    sent = [0]

    def handled():
        v = history[-1][2] if history else {}
        return int(v.get('frames_processed', 0)) + int(v.get('dropped_total', 0))

    def send(encoding, n, wait=True):
        for _ in range(n):
            stamp[0] += 33_000_000
            header = M.make_header(stamp[0], 'cam_optical')
            if encoding == 'rgb8':
                msg = M.rgb_to_image(TEXTURE, header)
            else:     # 16-bit colour: not an encoding the node reads
                msg = Image(header=header, height=4, width=4, encoding='rgb16', step=24, data=bytes(96))
            pub_info.publish(M.K_to_camera_info(np.array([[100.0, 0, 80], [0, 100.0, 64], [0, 0, 1]]), W, H, header))
            for t in (stamp[0] - 16_000_000, stamp[0] + 16_000_000):      # odometry around the image
                pub_odom.publish(PM.matrix_to_odometry(np.eye(4), t, 'base_link', frame_id='odom'))
            pub_img.publish(msg)
            sent[0] += 1
            if wait:    # one at a time: no image is replaced while the node is busy
                assert wait_for(lambda: handled() == sent[0], timeout=30.0, spin=spin), history[-1:]

    def received(n):
        return history and history[-1][2].get('frames_received') == str(n)
    try:
        assert wait_for(lambda: all(matched.get(t) == 1 for t in ('image', 'info', 'odom')),
                        timeout=60.0, spin=spin), f'the node never subscribed: {matched}'
        send('rgb8', 10, wait=False)          # a burst: the node replaces waiting images (busy), none faulty
        assert wait_for(lambda: received(10) and handled() == 10, timeout=60.0, spin=spin), history[-1:]
        burst = history[-1]
        send('rgb8', 8)
        send('rgb16', 2)                       # 2 of 20: 10 %, not above 30 %
        assert wait_for(lambda: received(20), timeout=60.0, spin=spin), history[-1:]
        n = len(history)
        assert wait_for(lambda: len(history) >= n + 2, timeout=20.0, spin=spin)
        below = history[-1]
        send('rgb16', 8)                       # 10 of 28: 36 %
        assert wait_for(lambda: received(28) and 'rejected as faulty' in history[-1][1], timeout=60.0, spin=spin), \
            history[-1:]
        above = history[-1]
        # a subscriber that asks for more than depth/image offers (transient local): incompatible QoS, reported
        from rclpy.qos import DurabilityPolicy
        node.create_subscription(Image, '/depth/image', lambda m: None,
                                 QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        assert wait_for(lambda: history[-1][2].get('qos_incompatible.depth/image', '0') != '0', timeout=20.0,
                        spin=spin), history[-1]
        qos_report = history[-1]
    finally:
        code, out = stop_process(proc)
    assert code == 0, out
    busy = int(burst[2].get('dropped.busy', 0))
    print(f'burst of 10: {busy} replaced while busy')
    assert burst[2]['drop_share_window'] == '0.0' and 'rejected as faulty' not in burst[1], \
        (burst[:2], {k: v for k, v in burst[2].items() if k.startswith(('dropped', 'faults'))})
    assert int(burst[2]['dropped_total']) == busy, burst[2]      # only busy drops: the textured images are fine
    assert below[2]['dropped.unsupported_encoding'] == '2' and below[2]['drop_share_window'] == '0.1', below
    assert 'rejected as faulty' not in below[1] and below[0] <= WARN, below[:2]
    assert above[0] == WARN and above[2]['dropped.unsupported_encoding'] == '10', above[:2]
    assert abs(float(above[2]['drop_share_window']) - 10 / 28) < 1e-3
    assert int(qos_report[2]['faults.incompatible_qos']) >= 1 and qos_report[0] >= WARN, qos_report[:2]
    assert "incompatible QoS on 'depth/image'" in out, out[-2000:]
