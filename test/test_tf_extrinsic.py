"""The camera mount from TF (extrinsic_source; dpv_sensor.ros.extrinsic) through the node process over real DDS.

- A rendered sequence written as a bag with odometry of base_link (the camera 0.3 m up and turned into an optical
  frame) and the mount on /tf_static as the chain base_link -> camera_link -> cam_optical, replayed into two nodes:
  /par types T_base_camera, /tf types nothing (auto looks the mount up on TF). Both publish the same depth for the
  same images, and /tf reports its source and the mount in /diagnostics.
- No transform: each image is dropped with a WARN naming both frames, counted (dropped.no_extrinsic,
  faults.no_extrinsic), nothing is published and the node stays up; once /tf_static carries the mount, depth comes.
- A second /tf_static publisher closes a loop through the mount's path (base_link -> camera_link -> cam -> base_link):
  the depth stays that of a clean run (abs_rel within 0.01 per frame, no reset), faults.tf_loop counts it once as it
  arrives, one WARN names the frames, /diagnostics stays at level WARN while it lasts.
- Two /tf_static publishers take turns on camera_link -> cam with values that differ in rotation only: each return
  counted (faults.tf_mount_flip), WARN, level WARN, the mount held at the value before the disagreement.
"""
import threading

import numpy as np
import pytest

from ros_helpers import assert_clean_exits, start_node, stop_all, wait_for
from stream_driver import FAST_PARAMS, StreamDriver, params_args
from test_node_integration import COMMON, FRAMES, H, START_NS, T_BASE_CAMERA, W, ros_args
from dpv_sensor.ros import msgs as M
from dpv_sensor.data import rosbag_io as R
from dpv_sensor.client.ros_io import BagPlayer, OutputCollector


@pytest.fixture(scope='module')
def tf_bag(tmp_path_factory):
    from dpv_sensor.data.synthetic import render_sequence
    seq = render_sequence(3, FRAMES, width=W, height=H)
    bag = tmp_path_factory.mktemp('bags') / 'base_link_tf_static'
    R.write_sequence_bag(bag, seq, odom_rate=60.0, start_ns=START_NS, T_base_camera=T_BASE_CAMERA,
                         camera_frame='cam_optical', odom_frame='map', tf_static=True, camera_link='camera_link',
                         progress=False)
    return bag


def test_the_mount_from_tf_static_gives_the_depth_of_the_parameter(tf_bag, observer):
    node, executor = observer
    spin = lambda t: executor.spin_once(timeout_sec=t)  # noqa: E731
    par = OutputCollector(node, namespace='/par', diagnostics_name='par/dpv_sensor: depth camera')
    tf = OutputCollector(node, namespace='/tf', diagnostics_name='tf/dpv_sensor: depth camera')
    env = {'OMP_NUM_THREADS': '1'}
    common = {**COMMON, 'pose_refinement': 'off'}      # the mount is under test, not the window (half the time)
    proc_par = start_node(ros_args({**common, 'T_base_camera': T_BASE_CAMERA, 'extrinsic_source': 'parameter'},
                                   ['-r', '__ns:=/par']), env=env)
    proc_tf = start_node(ros_args({**common, 'extrinsic_source': 'auto'}, ['-r', '__ns:=/tf']), env=env)
    player = BagPlayer(node, tf_bag, rate=0.25)
    played = {}
    try:
        ready = wait_for(lambda: all(c.diagnostics.get('measurement_model') == 'classical'
                                     and c.diag_int('publishers.image') == 1 and c.diag_int('publishers.odom') == 1
                                     for c in (par, tf)), timeout=60.0, spin=spin)
        assert proc_par.poll() is None and proc_tf.poll() is None, 'a node exited early'
        assert ready, f'the nodes never got ready: par {par.diagnostics} tf {tf.diagnostics}'
        assert not player.wait_for_subscribers(['/image', '/camera_info', '/odom'], min_count=2, timeout=10.0,
                                               spin=spin)
        assert not player.wait_for_subscribers(['/tf_static'], min_count=1, timeout=10.0, spin=spin)
        thread = threading.Thread(target=lambda: played.update(stats=player.play()), daemon=True)
        thread.start()
        done = wait_for(lambda: not thread.is_alive()
                        and all(c.diag_int('frames_processed') + c.diag_int('dropped_total') == FRAMES
                                and c.diag_int('outputs_published', -1) == len(c.complete()) for c in (par, tf)),
                        timeout=120.0, spin=spin)
        assert done, f'replay did not finish: par {par.diagnostics} tf {tf.diagnostics}'
    finally:
        exits = stop_all(proc_par, proc_tf)
        player.stop()
    assert_clean_exits(exits)
    assert par.diagnostics['extrinsic_source'] == 'parameter' and tf.diagnostics['extrinsic_source'] == 'tf (auto)'
    assert tf.diagnostics['extrinsic'].startswith("'base_link' -> 'cam_optical' xyz [0.050, -0.020, 0.300] q "
                                                  '[-0.5000, 0.5000, -0.5000, 0.5000]'), tf.diagnostics
    drops = {name: {k: v for k, v in c.diagnostics.items() if k.startswith(('dropped', 'faults', 'frames'))}
             for name, c in (('tf', tf), ('par', par))}                      # the reasons, not a truncated dict
    # no image is lost for want of the mount; one arriving while a keyframe still runs may be (counted as busy)
    for c in (tf, par):
        assert c.diag_int('dropped_total') == c.diag_int('dropped.busy', 0) <= 1, drops
    outs_par = {r.stamp_ns: M.image_to_float(r.depth) for r in par.complete()}
    outs_tf = {r.stamp_ns: M.image_to_float(r.depth) for r in tf.complete()}
    both = set(outs_tf) & set(outs_par)
    assert len(both) >= 4 and len(both) >= max(len(outs_tf), len(outs_par)) - 1, (sorted(outs_tf), sorted(outs_par))
    for stamp in both:
        depth = outs_par[stamp]
        assert np.isfinite(depth).mean() > 0.3
        np.testing.assert_allclose(outs_tf[stamp], depth, rtol=1e-5, atol=1e-5, equal_nan=True)


def _publish_mount(drv: StreamDriver):
    """The mount base_link -> cam on /tf_static (latched): the driver's odometry of base_link is the camera pose."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from tf2_msgs.msg import TFMessage
    from dpv_sensor.ros.tf_publisher import tf_message, transform_stamped
    qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    pub = drv.node.create_publisher(TFMessage, '/tf_static', qos)
    assert wait_for(lambda: pub.get_subscription_count() >= 1, timeout=20.0, spin=drv.spin), \
        'the node does not subscribe /tf_static'
    pub.publish(tf_message([transform_stamped(np.eye(4), drv.stamp_ns(0), 'base_link', 'cam')]))
    return pub


def test_no_transform_warns_counts_and_publishes_nothing_until_tf_static_arrives():
    # each image without a mount waits odom_wait_timeout for it before it is dropped: 1 s, not the driver's 3 s
    drv = StreamDriver(params_args({**FAST_PARAMS, 'extrinsic_source': 'auto', 'odom_wait_timeout': 1.0}), frames=16,
                       name='no_mount')
    n_without = 4
    try:
        drv.wait_ready()
        for i in range(n_without):
            drv.send(i, drv.stamp_ns(i))
            assert drv.wait_accounted(i + 1), drv.outputs.diagnostics
        diag = drv.wait_diagnostics()
        assert drv.proc.poll() is None
        assert int(diag['dropped.no_extrinsic']) == n_without and int(diag['faults.no_extrinsic']) == n_without, diag
        assert drv.outputs.depth_count == 0 and diag['extrinsic_source'] == 'tf (auto)', diag
        assert diag['extrinsic'].startswith('waiting for TF'), diag
        pub = _publish_mount(drv)
        for i in range(n_without, 16):
            drv.send(i, drv.stamp_ns(i))
            assert drv.wait_accounted(i + 1), drv.outputs.diagnostics
        assert wait_for(lambda: drv.outputs.depth_count >= 3, timeout=30.0, spin=drv.spin), drv.outputs.diagnostics
        diag = drv.wait_diagnostics()
        del pub
    finally:
        log = drv.stop()
    assert drv.code == 0, log
    assert int(diag['dropped.no_extrinsic']) == n_without, diag      # every later image found the mount
    assert int(diag['frames_processed']) == 16 - n_without, diag
    assert diag['extrinsic'].startswith("'base_link' -> 'cam' xyz [0.000, 0.000, 0.000]"), diag
    assert "no transform from 'base_link' to 'cam' on /tf_static or /tf yet" in log, log
    assert 'set T_base_camera or publish the camera mount' in log and 'WARN' in log, log
    assert "camera mount from TF: 'base_link' -> 'cam'" in log, log
    assert 'camera mount=tf (auto): looked up on /tf_static and /tf' in log, log          # the starting line
    assert min(drv.outputs.order) > drv.stamp_ns(n_without - 1)       # no output for an image without a mount


# ----------------------------------------------------------------------------------------------------
# TF faults on the mount's path: a loop, publishers that disagree
# ----------------------------------------------------------------------------------------------------

def _rigid(axis, deg: float, t) -> np.ndarray:
    from scipy.spatial.transform import Rotation
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.radians(deg) * np.asarray(axis, float) / np.linalg.norm(axis)).as_matrix()
    T[:3, 3] = t
    return T


# base_link -> camera_link -> cam composes to the identity, the mount of the driver's odometry (base_link tracks cam)
LINK = _rigid((1.0, 2.0, 2.0), 23.0, (0.3, -0.4, 1.2))
# a second publisher's link cam -> base_link closes a loop; taken as the mount it would be 30 deg and 0.5 m off
CLOSING = _rigid((0.0, 0.0, 1.0), 30.0, (0.5, 0.1, 0.0))
LOOP_TEXT = "'base_link' -> 'camera_link' -> 'cam' -> 'base_link'"
LOOP_FRAMES, LOOP_AT = 14, 6
WARN_LEVEL = 1                         # diagnostic_msgs/DiagnosticStatus.WARN


def _latched_tf_static(drv: StreamDriver):
    """A publisher of /tf_static with tf2's static QoS (reliable, transient local), matched by the node."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from tf2_msgs.msg import TFMessage
    qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    pub = drv.node.create_publisher(TFMessage, '/tf_static', qos)
    assert wait_for(lambda: pub.get_subscription_count() >= 1, timeout=20.0, spin=drv.spin), \
        'the node does not subscribe /tf_static'
    return pub


def _tf(*links):
    from dpv_sensor.ros.tf_publisher import tf_message, transform_stamped
    return tf_message([transform_stamped(T, 0, parent, child) for parent, child, T in links])


def _mount_of(diag: dict) -> np.ndarray:
    """The 7 numbers (xyz, q xyzw) of /diagnostics extrinsic "'base' -> 'image' xyz [..] q [..]"."""
    import re
    return np.array([float(v) for v in re.findall(r'-?\d+\.\d+', diag['extrinsic'].split('xyz', 1)[1])])


def _abs_rel_by_frame(drv: StreamDriver) -> dict:
    """{frame index: abs_rel of its published depth against the rendered depth} (valid GT within 0.3-8 m)."""
    out = {}
    for rec in drv.outputs.complete():
        i = round((rec.stamp_ns - drv.stamp_ns(0)) * 30.0 / 1e9)
        depth, gt = M.image_to_float(rec.depth), drv.seq.depth(i)
        ok = np.isfinite(depth) & (depth > 0) & (gt >= 0.3) & (gt <= 8.0)
        out[i] = float(np.mean(np.abs(depth[ok] - gt[ok]) / gt[ok]))
    return out


def _mount_run(name: str, loop: bool) -> tuple[dict, dict, int, str, str]:
    """LOOP_FRAMES frames one at a time to a node with the identity mount: from the parameter (loop False) or as
    the chain LINK, inv(LINK) on /tf_static, a second publisher closing the loop after LOOP_AT frames (loop True).
    ({frame: abs_rel}, diagnostics, level, level message, log)."""
    source = 'tf' if loop else 'parameter'
    drv = StreamDriver(params_args({**FAST_PARAMS, 'extrinsic_source': source}), frames=LOOP_FRAMES, name=name)
    try:
        drv.wait_ready()
        if loop:
            robot = _latched_tf_static(drv)
            robot.publish(_tf(('base_link', 'camera_link', LINK), ('camera_link', 'cam', np.linalg.inv(LINK))))
        for i in range(LOOP_FRAMES):
            if loop and i == LOOP_AT:
                other = _latched_tf_static(drv)
                other.publish(_tf(('cam', 'base_link', CLOSING)))
                out = drv.outputs         # counted and shown as the link arrives, before the next image
                assert wait_for(lambda: out.diag_int('faults.tf_loop') == 1 and out.diagnostics_level == WARN_LEVEL
                                and out.diagnostics.get('extrinsic_fault', '').startswith('TF loop'),
                                timeout=20.0, spin=drv.spin), out.diagnostics
            drv.send(i, drv.stamp_ns(i))
            assert drv.wait_accounted(i + 1), drv.outputs.diagnostics
        out = drv.outputs
        assert wait_for(lambda: out.diag_int('outputs_published', -1) == len(out.complete()), timeout=30.0,
                        spin=drv.spin), out.diagnostics
        diag = drv.wait_diagnostics()
        level, message = out.diagnostics_level, out.diagnostics_message
        by_frame = _abs_rel_by_frame(drv)
    finally:
        log = drv.stop()
    assert drv.code == 0 and 'Traceback' not in log, log
    return by_frame, diag, level, message, log


def test_a_tf_loop_keeps_the_depth_of_the_mount_before_it_counts_once_and_warns():
    clean, diag_clean, _, _, _ = _mount_run('tf_clean', loop=False)
    looped, diag, level, message, log = _mount_run('tf_loop', loop=True)
    after = [i for i in clean if i >= LOOP_AT]
    assert len(after) >= 4 and sorted(looped) == sorted(clean), (sorted(looped), sorted(clean))
    # the same depth as the clean run after the loop: no reset, abs_rel within 0.01 frame by frame and in the mean
    assert diag['filter_resets'] == diag_clean['filter_resets'], (diag, diag_clean)
    for i in after:
        assert abs(looped[i] - clean[i]) < 0.01, (i, looped[i], clean[i])
    np.testing.assert_allclose(_mount_of(diag), [0.0] * 6 + [1.0], atol=1e-3)     # the identity kept
    assert int(diag['faults.tf_loop']) == 1 and int(diag['extrinsic_changes']) == 0, diag
    assert int(diag['dropped_total']) == int(diag.get('dropped.busy', 0)) == 0, diag
    # level WARN while the loop is there, saying why; one WARN line naming the frames
    assert level == WARN_LEVEL and f'TF loop on the camera mount path: {LOOP_TEXT}' in message, message
    assert diag['extrinsic_fault'] == f'TF loop on the camera mount path: {LOOP_TEXT}'
    assert log.count(f"TF loop on the camera mount's path 'base_link' -> 'cam': {LOOP_TEXT}") == 1, log
    assert 'keeping the last good mount xyz' in log and 'camera mount changed on TF' not in log, log


def test_two_tf_static_publishers_that_disagree_warn_count_each_message_and_hold_the_mount():
    """The robot's publisher latches camera_link -> cam = inv(LINK) (the identity mount); a second publisher's
    value turns 5 deg more without moving. Once the first value is older than a burst, the second publisher's value
    arrives (a change), then the first's and the second's again: two returns, counted, the mount held at the first
    publisher's (the latest, the second's, would turn the camera 5 deg)."""
    from dpv_sensor.stream.transform_tree import STATIC_BURST_S
    import time
    turned = np.linalg.inv(LINK)
    turned[:3, :3] = _rigid((0.0, 1.0, 0.0), 5.0, (0.0, 0.0, 0.0))[:3, :3] @ turned[:3, :3]
    drv = StreamDriver(params_args({**FAST_PARAMS, 'extrinsic_source': 'tf'}), frames=8, name='tf_flip')
    try:
        drv.wait_ready()
        robot, other = _latched_tf_static(drv), _latched_tf_static(drv)
        first = _tf(('base_link', 'camera_link', LINK), ('camera_link', 'cam', np.linalg.inv(LINK)))
        robot.publish(first)
        drv.send(0, drv.stamp_ns(0))
        assert drv.wait_accounted(1) and wait_for(lambda: drv.outputs.diagnostics.get('extrinsic', '').startswith(
            "'base_link' -> 'cam' xyz"), timeout=10.0, spin=drv.spin), drv.outputs.diagnostics
        mount_seen = time.monotonic()                   # the first value had arrived: frame 0 used it
        for i in range(1, 4):
            drv.send(i, drv.stamp_ns(i))
            assert drv.wait_accounted(i + 1), drv.outputs.diagnostics
        i = 4
        # not a synchronisation: the rule under test is the value's age (two latched values within a burst are a
        # conflict at once), and here the first value must be older than that when the second arrives
        wait_for(lambda: time.monotonic() - mount_seen > STATIC_BURST_S + 0.5, timeout=10.0, spin=drv.spin)
        second = _tf(('camera_link', 'cam', turned))
        for pub, msg in ((other, second), (robot, first), (other, second)):
            pub.publish(msg)
        out = drv.outputs
        assert wait_for(lambda: out.diag_int('faults.tf_mount_flip') == 2 and out.diagnostics_level == WARN_LEVEL,
                        timeout=20.0, spin=drv.spin), out.diagnostics
        for k in range(i, i + 3):
            drv.send(k, drv.stamp_ns(k))
            assert drv.wait_accounted(k + 1), drv.outputs.diagnostics
        diag = drv.wait_diagnostics()
        message = out.diagnostics_message
    finally:
        log = drv.stop()
    assert drv.code == 0 and 'Traceback' not in log, log
    assert int(diag['faults.tf_mount_flip']) == 2 and int(diag.get('faults.tf_conflicting_parents', 0)) == 0, diag
    np.testing.assert_allclose(_mount_of(diag), [0.0] * 6 + [1.0], atol=1e-3)     # held at the first publisher's
    assert int(diag['extrinsic_changes']) == 0 and 'camera mount changed on TF' not in log, log
    assert int(diag['frames_processed']) == i + 3, diag
    fault = "TF publishers disagree on the camera mount path: 'camera_link' -> 'cam' (transforms, held)"
    assert diag['extrinsic_fault'] == fault and fault in message, (diag, message)
    assert "/tf_static publishers disagree on 'camera_link' -> 'cam'" in log and 'WARN' in log, log
