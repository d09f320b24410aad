"""Input faults a camera or an odometry source can produce, replayed into the node process over DDS: degenerate
images (all black, all white, saturated, noise), images with an empty frame_id, and odometry that repeats a stamp
(identically, and with a pose 5 cm off).

The client sends one image at a time (odometry and camera_info at its stamp first) and waits until the node has
accounted for it (frames_processed + dropped_total in /diagnostics), so the node is never busy when an image arrives
and every image reaches the check under test. One replay serves the tests of this module.
"""
import re

import numpy as np
import pytest

from ros_helpers import start_node, stop_process, wait_for
from dpv_sensor.ros import msgs as M
from dpv_sensor.ros import pose_msgs as PM
from dpv_sensor.stream.pose_buffer import NS

W, H = 160, 128
BASE_NS = 1_760_000_000 * NS
# frame index -> what is sent instead of the rendered image; each run of consecutive frames is one episode
DEGENERATE = {**{i: 'black' for i in (8, 9, 10)}, **{i: 'white' for i in (14, 15)},
              **{i: 'saturated' for i in (19, 20, 21)}, **{i: 'noise' for i in (25, 26, 27)}}
EPISODES = [(8, 3, 'black'), (14, 2, 'saturated'), (19, 3, 'saturated'), (25, 3, 'noise')]   # start, length, reason
EMPTY_FRAME_ID = range(31, 37)       # images with header.frame_id ''
FRAMES = 38
DUPLICATE_ODOM = 3                   # odometry at this frame's stamp is sent twice, identical
CONFLICT_ODOM = 5                    # ... and at this one a second time, 5 cm off
CONFLICT_OFFSET_M = 0.05


def stamp_ns(i: int) -> int:
    return BASE_NS + int(round(i * NS / 30))


def degenerate_image(kind: str, rgb: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    if kind == 'black':
        return np.zeros_like(rgb)
    if kind == 'white':
        return np.full_like(rgb, 255)
    if kind == 'saturated':       # the scene, overexposed: every channel at 250 or more
        return np.clip(rgb.astype(np.int32) + 250, 0, 255).astype(np.uint8)
    return rng.integers(0, 256, size=rgb.shape, dtype=np.uint8)


@pytest.fixture(scope='module')
def replay():
    """Run the node, send the sequence; returns (diagnostics, node log, {stamp_ns: output frame_id})."""
    from diagnostic_msgs.msg import DiagnosticArray  # noqa: F401  (the collector's types must import)
    from nav_msgs.msg import Odometry
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import CameraInfo, Image

    from dpv_sensor.data.synthetic import render_sequence
    from dpv_sensor.client.node_process import ClientNode
    from dpv_sensor.client.ros_io import OutputCollector

    seq = render_sequence(4, FRAMES, width=W, height=H)
    rng = np.random.default_rng(0)
    client = ClientNode('input_fault_client')
    node, executor = client.node, client.executor
    spin = lambda t: executor.spin_once(timeout_sec=t)  # noqa: E731
    qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.VOLATILE)
    pubs = {'image': node.create_publisher(Image, '/cam/image', qos),
            'camera_info': node.create_publisher(CameraInfo, '/cam/camera_info', qos),
            'odom': node.create_publisher(Odometry, '/odom', qos)}
    outputs = OutputCollector(node)
    params = {'measurement': 'classical', 'processing_width': W, 'processing_height': H, 'num_planes': 32,
              'keyframe_max_interval': 1, 'input_depth': 50, 'diagnostics_period': 0.1,
              'extrinsic_source': 'parameter'}
    args = ['--ros-args'] + [a for k, v in params.items() for a in ('-p', f'{k}:={v}')] + [
        '-r', 'image:=/cam/image', '-r', 'camera_info:=/cam/camera_info', '-r', 'odom:=/odom']
    proc = start_node(args, env={'OMP_NUM_THREADS': '1'})
    accounted = lambda: outputs.diag_int('frames_processed') + outputs.diag_int('dropped_total')  # noqa: E731
    try:
        # the estimator is built, the node subscribes reliable (as the client offers: input_reliability auto) and
        # the collector is matched with its outputs
        ready = wait_for(lambda: outputs.diagnostics.get('measurement_model') == 'classical'
                         and all(outputs.diagnostics.get(f'input_qos.{k}') == 'reliable' for k in pubs)
                         and all(outputs.diag_int(f'publishers.{k}') == 1 for k in pubs)
                         and all(p.get_subscription_count() == 1 for p in pubs.values())
                         and outputs.subs[0].get_publisher_count() == 1, timeout=90.0, spin=spin)
        assert proc.poll() is None, 'node exited early:\n' + stop_process(proc)[1]
        assert ready, f'the node never got ready: {outputs.diagnostics}'
        for i in range(FRAMES):
            t = stamp_ns(i)
            pose = seq.pose(i)
            pubs['odom'].publish(PM.matrix_to_odometry(pose, t, 'base_link', 'odom'))
            if i in (DUPLICATE_ODOM, CONFLICT_ODOM):
                other = pose.copy()
                if i == CONFLICT_ODOM:
                    other[0, 3] += CONFLICT_OFFSET_M
                pubs['odom'].publish(PM.matrix_to_odometry(other, t, 'base_link', 'odom'))
            frame_id = '' if i in EMPTY_FRAME_ID else 'cam'
            pubs['camera_info'].publish(M.K_to_camera_info(seq.K, W, H, t, frame_id))
            rgb = seq.image(i)
            if i in DEGENERATE:
                rgb = degenerate_image(DEGENERATE[i], rgb, rng)
            pubs['image'].publish(M.rgb_to_image(rgb, t, frame_id))
            done = wait_for(lambda n=i + 1: accounted() >= n, timeout=60.0, spin=spin)
            assert done and proc.poll() is None, f'image {i} was not accounted for: {outputs.diagnostics}'
        # the last output and one more diagnostics message
        count = outputs.diagnostics_count
        wait_for(lambda: outputs.diagnostics_count >= count + 2, timeout=10.0, spin=spin)
        diag = dict(outputs.diagnostics)
        frames_out = {r.stamp_ns: r.frame_id for r in outputs.complete()}
    finally:
        code, log = stop_process(proc)
        client.close()
    assert code == 0, log
    assert int(diag['frames_received']) == FRAMES and accounted() == FRAMES, diag
    return diag, log, frames_out


def test_degenerate_images_are_dropped_counted_and_logged_once_per_episode(replay):
    diag, log, frames_out = replay
    # no depth for them, every one counted, and the node kept going
    assert not [i for i in DEGENERATE if stamp_ns(i) in frames_out], sorted(frames_out)
    assert int(diag['dropped.degenerate_image']) == len(DEGENERATE), diag
    assert int(diag['degenerate_episodes']) == len(EPISODES), diag
    assert any(stamp_ns(i) in frames_out for i in range(EPISODES[-1][0] + 3, FRAMES)), 'no output after the noise'
    # one line when an episode starts (with the reason), one when it ends (with the count)
    starts = re.findall(r'degenerate images from (\d+\.\d+) s on \((\w+)', log)
    ends = re.findall(r'degenerate images ended at (\d+\.\d+) s: (\d+) dropped', log)
    assert [(round(float(t), 3), r) for t, r in starts] == \
        [(round(stamp_ns(i) / NS, 3), reason) for i, _n, reason in EPISODES], log
    assert [(round(float(t), 3), int(n)) for t, n in ends] == \
        [(round(stamp_ns(i + n) / NS, 3), n) for i, n, _r in EPISODES], log


def test_empty_frame_id_is_warned_once_counted_and_replaced(replay):
    diag, log, frames_out = replay
    assert int(diag['faults.empty_frame_id']) == len(EMPTY_FRAME_ID), diag
    assert log.count('empty header.frame_id') == 1, log
    assert "the outputs use the frame_id parameter 'camera_optical_frame'" in log
    empty = {stamp_ns(i) for i in EMPTY_FRAME_ID}
    replaced = [f for s, f in frames_out.items() if s in empty]
    assert replaced and set(replaced) == {'camera_optical_frame'}, frames_out
    assert {f for s, f in frames_out.items() if s not in empty} == {'cam'}, frames_out


def test_conflicting_odometry_is_warned_counted_and_the_first_kept(replay):
    diag, log, _frames_out = replay
    assert int(diag['faults.odometry_conflict']) == 1, diag
    assert f'conflicting odometry at {stamp_ns(CONFLICT_ODOM) / NS:.3f} s: two poses 0.050 m and 0.0 deg apart; ' \
        'keeping the first' in log, log
    # the identical repeat is ignored quietly: counted apart, no warning
    assert int(diag['odometry_duplicates']) == 1, diag
    assert log.count('conflicting odometry') == 1
    # the image at the conflicting stamp was used (with the first pose)
    assert int(diag.get('dropped_total')) == len(DEGENERATE), diag
