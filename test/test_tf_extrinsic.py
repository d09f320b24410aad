"""The camera mount from TF (extrinsic_source; dpv_sensor.ros.extrinsic) through the node process over real DDS.

- A rendered sequence written as a bag with odometry of base_link (the camera 0.3 m up and turned into an optical
  frame) and the mount on /tf_static as the chain base_link -> camera_link -> cam_optical, replayed into two nodes:
  /par types T_base_camera, /tf types nothing (auto looks the mount up on TF). Both publish the same depth for the
  same images, and /tf reports its source and the mount in /diagnostics.
- No transform: each image is dropped with a WARN naming both frames, counted (dropped.no_extrinsic,
  faults.no_extrinsic), nothing is published and the node stays up; once /tf_static carries the mount, depth comes.
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
    drv = StreamDriver(params_args({**FAST_PARAMS, 'extrinsic_source': 'auto'}), frames=16, name='no_mount')
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
