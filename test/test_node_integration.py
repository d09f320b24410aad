"""The node end to end over real DDS: a rendered sequence as a rosbag2, replayed into two node processes.

The bag is played in-process with client.ros_io.BagPlayer (started once both nodes report, in /diagnostics, that they
see its publishers); `bag record` (BagRecorder) records node A's outputs, which are then exported. Node A (defaults:
32FC1, input resolution) and node B (namespace /mm: 16UC1, processing resolution 80x64, min_confidence, someone
subscribed to its point cloud) run side by side on the same replay. Checked:
- every estimator output arrives as depth + confidence + depth/camera_info with the image's exact stamp and frame_id;
- node A publishes exactly the keyframes the Estimator produces offline on the same frames (when it dropped none),
  32FC1 at the image size with the image's K, and its abs_rel against the rendered ground truth is within 10 % of
  the offline Estimator's on the same frames;
- node B publishes 16UC1 at 80x64 with K scaled to that size, no depth below min_confidence, and an organised
  XYZRGB point cloud consistent with its depth; node A, which nobody subscribes to for points, computes none.
"""
import sys
import threading

import numpy as np
import pytest
import rclpy

from ros_helpers import start_node, stop_process, wait_for, write_rendered_bag
from dpv_sensor.ros import msgs as M
from dpv_sensor.ros import cloud_msgs as C
from dpv_sensor import params as P
from dpv_sensor.data import rosbag_io as R
from dpv_sensor.data.bag_export import export_depth_bag
from dpv_sensor.stream.pose_buffer import NS
from dpv_sensor.client.ros_io import BagPlayer, BagRecorder, OutputCollector

W, H = 160, 128
FRAMES = 36
START_NS = 1_700_000_000_123_456_789
T_BASE_CAMERA = [0.05, -0.02, 0.3, -0.5, 0.5, -0.5, 0.5]   # base_link (x forward, z up) -> optical frame
# the causal window: every keyframe after the first has its output at once (these tests pair outputs with frames)
COMMON = {'measurement': 'classical', 'processing_width': W, 'processing_height': H, 'num_planes': 32,
          'input_reliability': 'reliable', 'input_depth': 50, 'odom_wait_timeout': 2.0, 'diagnostics_period': 0.1,
          'window_mode': 'causal', 'extrinsic_source': 'parameter'}
REMAP = ['-r', 'image:=/image', '-r', 'camera_info:=/camera_info', '-r', 'odom:=/odom']


def ros_args(params: dict, extra=()):
    out = ['--ros-args']
    for k, v in params.items():
        if isinstance(v, list):
            v = '[' + ','.join(repr(float(x)) for x in v) + ']'
        out += ['-p', f'{k}:={v}']
    return out + REMAP + list(extra)


def abs_rel(depth, gt, d_min, d_max):
    valid = np.isfinite(depth) & (depth > 0) & (gt >= d_min) & (gt <= d_max)
    return float(np.mean(np.abs(depth[valid] - gt[valid]) / gt[valid])), int(valid.sum())


@pytest.fixture(scope='module')
def scene(tmp_path_factory):
    return write_rendered_bag(tmp_path_factory, 3, FRAMES, W, H, 'synthetic', start_ns=START_NS,
                              T_base_camera=T_BASE_CAMERA)


def run_estimator(seq, stamps_ns, frames, **overrides):
    """The Estimator in-process on `frames` (indices) with ground-truth poses: {stamp_ns: DepthOutput}."""
    import torch
    from dpv_sensor.stream.estimator import Estimator, EstimatorConfig
    from dpv_sensor.stream.frame import Frame
    values = P.defaults()
    values.update({k: v for k, v in COMMON.items() if k in values})
    values.update(overrides)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        est = Estimator(EstimatorConfig.from_params(P.validate(values)))
        outs = {}
        for i in frames:
            out = est.push(Frame(stamp=stamps_ns[i] / 1e9, image=seq.image(i), K_33=seq.K,
                                 T_world_cam_44=seq.pose(i), frame_id='cam_optical'))
            if out is not None:
                assert out.stamp == stamps_ns[i] / 1e9, 'causal window outputs belong to the frame just pushed'
                outs[stamps_ns[i]] = out
    finally:
        torch.set_num_threads(threads)
    return outs


@pytest.fixture(scope='module')
def offline(scene):
    """What the Estimator gives in-process on all frames of the bag (ground-truth poses): {stamp_ns: DepthOutput}."""
    seq, _bag, summary = scene
    return run_estimator(seq, summary.image_stamps_ns, range(FRAMES))




def test_replayed_bag_gives_depth_for_every_keyframe_with_exact_headers(scene, offline, observer, tmp_path):
    seq, bag, summary = scene
    ref_outputs = offline
    node, executor = observer
    spin = lambda t: executor.spin_once(timeout_sec=t)  # noqa: E731
    a = OutputCollector(node, diagnostics_name='dpv_sensor: depth camera')
    b = OutputCollector(node, namespace='/mm', points=True, diagnostics_name='mm/dpv_sensor: depth camera')
    env = {'OMP_NUM_THREADS': '1'}
    proc_a = start_node(ros_args({**COMMON, 'T_base_camera': T_BASE_CAMERA}), env=env)
    proc_b = start_node(ros_args({**COMMON, 'T_base_camera': T_BASE_CAMERA, 'depth_encoding': '16UC1',
                                  'processing_width': 80, 'processing_height': 64, 'output_resolution': 'processing',
                                  'min_confidence': 0.3}, ['-r', '__ns:=/mm']), env=env)
    player = BagPlayer(node, bag, rate=0.2)
    recorder = BagRecorder(node, tmp_path / 'recorded', ['/depth/image', '/confidence/image', '/depth/camera_info'])
    played = {}
    try:
        # both nodes built their estimators, see the player's publishers on every input, and the collectors see
        # the nodes' outputs
        inputs = ('publishers.image', 'publishers.camera_info', 'publishers.odom')
        ready = wait_for(lambda: all(c.diagnostics.get('measurement_model') == 'classical'
                                     and all(c.diag_int(k) == 1 for k in inputs) for c in (a, b))
                         and a.subs[0].get_publisher_count() == 1 and b.subs[0].get_publisher_count() == 1,
                         timeout=60.0, spin=spin)
        assert proc_a.poll() is None and proc_b.poll() is None, 'a node exited early'
        assert ready, f'the nodes never got ready: A {a.diagnostics} B {b.diagnostics}'
        assert not player.wait_for_subscribers(min_count=2, timeout=10.0, spin=spin)
        assert wait_for(lambda: not recorder.poll(), timeout=20.0, spin=spin), 'recorder found no publishers'
        thread = threading.Thread(target=lambda: played.update(stats=player.play()), daemon=True)
        thread.start()
        # all images reached both nodes (reliable input) and every output the nodes counted has arrived here, at
        # the collectors and at the recorder (its own subscriptions: their last message can come a spin later)
        recorded = ('/depth/image', '/confidence/image', '/depth/camera_info')
        done = wait_for(lambda: not thread.is_alive() and a.diag_int('frames_received') == FRAMES
                        and b.diag_int('frames_received') == FRAMES
                        and a.diag_int('frames_processed') + a.diag_int('dropped_total') == FRAMES
                        and b.diag_int('frames_processed') + b.diag_int('dropped_total') == FRAMES
                        and a.diag_int('outputs_published', -1) == len(a.complete())
                        and b.diag_int('outputs_published', -1) == len(b.complete())
                        and all(recorder.counts.get(t, 0) >= a.diag_int('outputs_published', -1) for t in recorded),
                        timeout=60.0, spin=spin)
        assert done, (f'replay did not finish: A {a.diagnostics} complete={len(a.complete())}; '
                      f'B {b.diagnostics} complete={len(b.complete())}; recorded {recorder.counts}')
        assert played['stats'].published == player.total_messages
    finally:
        recorder.close()
        code_a, out_a = stop_process(proc_a)
        code_b, out_b = stop_process(proc_b)
        player.stop()
    assert code_a == 0 and code_b == 0, out_a + out_b
    assert 'Traceback' not in out_a + out_b, out_a + out_b

    image_stamps = set(summary.image_stamps_ns)
    # ---------------- node A: 32FC1 at the image size, exact headers, offline-equivalent keyframes
    outs_a = a.complete()
    assert len(outs_a) >= 4, f'too few outputs: {a.diagnostics}'
    assert len(outs_a) == len(a.by_stamp), 'an output arrived without its depth, confidence or camera_info'
    for rec in outs_a:
        assert rec.stamp_ns in image_stamps and rec.frame_id == 'cam_optical'
        for msg in (rec.depth, rec.confidence, rec.camera_info):
            assert M.stamp_to_ns(msg.header.stamp) == rec.stamp_ns and msg.header.frame_id == 'cam_optical'
        assert rec.depth.encoding == '32FC1' and rec.confidence.encoding == '32FC1'
        assert (rec.depth.width, rec.depth.height) == (W, H) == (rec.camera_info.width, rec.camera_info.height)
        K, size = M.camera_info_to_K(rec.camera_info)
        np.testing.assert_allclose(K, seq.K, rtol=1e-12)
    stamps_a = [r.stamp_ns for r in outs_a]
    assert stamps_a == sorted(stamps_a)
    idx = {t: i for i, t in enumerate(summary.image_stamps_ns)}
    if a.diag_int('dropped_total') == 0:
        assert set(stamps_a) == set(ref_outputs), 'node A and the offline Estimator disagree on the keyframes'
        reference = ref_outputs
    else:
        # newest-wins dropped frames on a busy machine, so the node chose other keyframes than an offline run over
        # every frame. Its keyframes are the first frame and every frame it published: the Estimator run on
        # exactly those frames (each one a keyframe) reproduces what the node computed.
        print(f'node A dropped frames: { {k: v for k, v in a.diagnostics.items() if k.startswith("dropped")} }')
        frames = [0] + [idx[s] for s in stamps_a]
        reference = run_estimator(seq, summary.image_stamps_ns, frames, keyframe_max_interval=1)
        assert set(stamps_a) == set(reference)
    d_min, d_max = 0.3, 8.0
    node_err = [abs_rel(M.image_to_float(a.by_stamp[s].depth), seq.depth(idx[s]), d_min, d_max)[0] for s in stamps_a]
    ref_err = [abs_rel(reference[s].depth_hw, seq.depth(idx[s]), d_min, d_max)[0] for s in stamps_a]
    print(f'abs_rel node {np.mean(node_err):.4f} offline {np.mean(ref_err):.4f} over {len(stamps_a)} keyframes')
    assert abs(np.mean(node_err) - np.mean(ref_err)) <= 0.1 * np.mean(ref_err)
    assert np.mean(ref_err) < 0.6      # the classical model does estimate depth on this scene
    assert a.diag_int('point_clouds_published') == 0 and a.diagnostics['measurement_model'] == 'classical'

    # ---------------- `bag record` of node A's outputs, exported to PNG (mm)
    assert recorder.counts == {t: len(outs_a) for t in ('/depth/image', '/confidence/image', '/depth/camera_info')}
    exported = export_depth_bag(tmp_path / 'recorded', tmp_path / 'export', progress=False)
    assert exported['frames'] == len(outs_a) and exported['without_confidence'] == 0
    import cv2
    for k, rec in enumerate(outs_a):
        mm = cv2.imread(str(tmp_path / 'export' / 'depth' / f'{k:06d}.png'), cv2.IMREAD_UNCHANGED)
        d = M.image_to_float(rec.depth)
        np.testing.assert_array_equal(mm, np.where(np.isfinite(d), np.round(np.nan_to_num(d).astype(np.float64) * 1000),
                                                   0))
    np.testing.assert_allclose(np.loadtxt(tmp_path / 'export' / 'K.txt'), seq.K, rtol=1e-12)

    # ---------------- node B: 16UC1 at the processing size, min_confidence, point cloud
    outs_b = b.complete()
    assert len(outs_b) >= 4
    # 160x128 -> 80x64 halves the focal lengths; pixel centres sit at integers, so c' = (c + 0.5) / 2 - 0.5
    (fx, fy), (cx, cy) = np.diag(seq.K)[:2], seq.K[:2, 2]
    K_b = np.array([[fx / 2, 0.0, (cx + 0.5) / 2 - 0.5], [0.0, fy / 2, (cy + 0.5) / 2 - 0.5], [0.0, 0.0, 1.0]])
    for rec in outs_b:
        assert rec.stamp_ns in image_stamps and rec.frame_id == 'cam_optical'
        assert rec.depth.encoding == '16UC1'
        assert (rec.depth.width, rec.depth.height) == (80, 64) == (rec.camera_info.width, rec.camera_info.height)
        np.testing.assert_allclose(M.camera_info_to_K(rec.camera_info)[0], K_b, rtol=1e-12)
        mm = np.frombuffer(bytes(rec.depth.data), '<u2').reshape(64, 80)
        conf = M.image_to_float(rec.confidence)
        assert np.all(mm[conf < 0.3] == 0), 'depth published below min_confidence'
        assert np.any(mm > 0)
    with_points = [r for r in outs_b if r.points is not None]
    assert with_points and b.diag_int('point_clouds_published') >= len(with_points)
    for rec in with_points:
        assert M.stamp_to_ns(rec.points.header.stamp) == rec.stamp_ns and rec.points.header.frame_id == 'cam_optical'
        assert (rec.points.height, rec.points.width, rec.points.is_dense) == (64, 80, False)
        xyz, rgb = C.pointcloud_to_xyzrgb(rec.points)
        mm = np.frombuffer(bytes(rec.depth.data), '<u2').reshape(-1).astype(np.float64)
        valid = mm > 0
        np.testing.assert_allclose(xyz[valid, 2], mm[valid] / 1000.0, atol=5.1e-4)
        assert np.isnan(xyz[~valid]).all()
        assert rgb[valid].max() > 0


def test_intrinsics_from_parameters(scene, observer):
    """`camera_info_source: parameters`: no camera_info subscription; the published depth/camera_info carries the
    fx, fy, cx, cy given as parameters (this scene's camera: cx 76.8, cy 63.4, so a swap shows), and the depth
    computed with them matches the rendered ground truth as well as with camera_info from the topic."""
    seq, bag, summary = scene
    fx, fy, cx, cy = (float(seq.K[0, 0]), float(seq.K[1, 1]), float(seq.K[0, 2]), float(seq.K[1, 2]))
    assert abs(cx - cy) > 10.0
    node, executor = observer
    spin = lambda t: executor.spin_once(timeout_sec=t)  # noqa: E731
    a = OutputCollector(node, diagnostics_name='dpv_sensor: depth camera')
    params = {**COMMON, 'T_base_camera': T_BASE_CAMERA, 'camera_info_source': 'parameters',
              'fx': fx, 'fy': fy, 'cx': cx, 'cy': cy}
    proc = start_node(ros_args(params), env={'OMP_NUM_THREADS': '1'})
    player = BagPlayer(node, bag, rate=0.3, topics=[R.IMAGE_TOPIC, R.ODOM_TOPIC])
    played = {}
    try:
        ready = wait_for(lambda: a.diagnostics.get('measurement_model') == 'classical'
                         and a.diag_int('publishers.image') == 1 and a.diag_int('publishers.odom') == 1
                         and a.subs[0].get_publisher_count() == 1, timeout=60.0, spin=spin)
        assert proc.poll() is None and ready, f'the node never got ready: {a.diagnostics}'
        assert node.count_subscribers('/camera_info') == 0, 'parameters mode subscribed to camera_info'
        assert not player.wait_for_subscribers(timeout=10.0, spin=spin)
        thread = threading.Thread(target=lambda: played.update(stats=player.play(duration=120.0)), daemon=True)
        thread.start()
        assert wait_for(lambda: len(a.complete()) >= 3, timeout=120.0, spin=spin), f'no outputs: {a.diagnostics}'
    finally:
        player.stop()
        code, out = stop_process(proc)
    assert code == 0 and 'Traceback' not in out, out
    idx = {t: i for i, t in enumerate(summary.image_stamps_ns)}
    errs = []
    for rec in a.complete():
        K, size = M.camera_info_to_K(rec.camera_info)
        assert size == (W, H)
        np.testing.assert_allclose(K, [[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], rtol=1e-12)
        errs.append(abs_rel(M.image_to_float(rec.depth), seq.depth(idx[rec.stamp_ns]), 0.3, 8.0)[0])
    assert np.mean(errs) < 0.6, errs


def test_bag_play_command_line_replays_exact_messages(tmp_path, observer):
    """`bag play` as its own process: waits until its publisher matched the subscriber (no fixed delay), keeps
    stamps and frame ids, follows ROS remapping, uses the recorded (reliable) QoS, and --rebase-stamps shifts stamps
    to the wall clock keeping their spacing."""
    from sensor_msgs.msg import Image
    import time
    node, executor = observer
    spin = lambda t: executor.spin_once(timeout_sec=t)  # noqa: E731
    rng = np.random.default_rng(0)
    n = 8
    seq = R.ArraySequence(rng.integers(0, 256, (n, 24, 32, 3), np.uint8), np.tile(np.eye(4), (n, 1, 1)),
                          np.array([[30.0, 0, 15.5], [0, 30.0, 11.5], [0, 0, 1]]), stamps=50.0 + np.arange(n) / 20)
    R.write_sequence_bag(tmp_path / 'bag', seq, camera_frame='cam', progress=False)
    got = []
    qos = rclpy.qos.QoSProfile(depth=50, reliability=rclpy.qos.ReliabilityPolicy.RELIABLE)
    node.create_subscription(Image, '/replayed', lambda m: got.append((M.stamp_to_ns(m.header.stamp), m)), qos)
    for extra in ([], ['--rebase-stamps']):
        got.clear()
        t0 = time.time_ns()
        player = start_node(['play', str(tmp_path / 'bag'), '--topics', '/image', '--wait-timeout', '30',
                             '--rate', '2', '--no-progress'] + extra
                            + ['--ros-args', '-r', '/image:=/replayed'],
                            executable=[sys.executable, '-m', 'dpv_sensor.tools.bag'])
        finished = wait_for(lambda: player.poll() is not None and len(got) == n, timeout=60.0, spin=spin)
        code, out = stop_process(player)
        assert code == 0 and finished, f'{len(got)} of {n} images arrived\n{out}'
        assert 'published 8 messages' in out and 'playing anyway' not in out, out
        stamps = [s for s, _m in got]
        expected = [50 * NS + i * NS // 20 for i in range(n)]
        if extra:
            assert stamps[0] >= t0 and np.allclose(np.diff(stamps), np.diff(expected) / 2, atol=1)   # rate 2
        else:
            assert stamps == expected
        assert {m.header.frame_id for _s, m in got} == {'cam'}
        np.testing.assert_array_equal(M.image_to_rgb(got[3][1]), seq.image(3))
