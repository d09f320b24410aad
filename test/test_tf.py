"""TF output (dpv_sensor.ros.tf_publisher): message building, and the node process over real DDS.

- TransformStamped from a 4x4 matrix (hand-computable rotation), the static frame pair rules;
- with publish_tf the node puts base_link -> image frame (T_base_camera) on /tf_static, latched (a subscriber that
  joins later gets it), as tf2_msgs/msg/TFMessage with tf2's type hash; without it, no TF publisher exists.
"""
import math

import numpy as np
import pytest

from ros_helpers import start_node, stop_process, wait_for
from test_node_integration import COMMON, ros_args
from dpv_sensor.ros import tf_publisher as TF
from dpv_sensor.stream.pose_buffer import make_pose

# tf2_msgs/msg/TFMessage of ROS 2 Jazzy (as `ros2 topic info -v /tf` reports it): the generated package must match
TFMESSAGE_HASH = 'RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087'
EXTRINSIC = [0.1, -0.2, 0.3, 0.0, 0.0, math.sqrt(0.5), math.sqrt(0.5)]   # 90 deg about z, then (0.1, -0.2, 0.3)


def test_transform_stamped_from_a_matrix():
    T = np.array([[0.0, -1.0, 0.0, 0.1], [1.0, 0.0, 0.0, -0.2], [0.0, 0.0, 1.0, 0.3], [0.0, 0.0, 0.0, 1.0]])
    msg = TF.transform_stamped(T, 1_700_000_000_500_000_000, 'base_link', 'cam_optical')
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1_700_000_000, 500_000_000)
    assert (msg.header.frame_id, msg.child_frame_id) == ('base_link', 'cam_optical')
    t, q = msg.transform.translation, msg.transform.rotation
    np.testing.assert_allclose([t.x, t.y, t.z], [0.1, -0.2, 0.3])
    np.testing.assert_allclose([q.x, q.y, q.z, q.w], [0.0, 0.0, math.sqrt(0.5), math.sqrt(0.5)], atol=1e-12)
    with pytest.raises(ValueError, match='base_link -> cam'):
        TF.transform_stamped(np.full((4, 4), np.nan), 0, 'base_link', 'cam')


def test_static_frame_pair_rules():
    assert TF.static_frames('base_link', 'cam_optical') == ('base_link', 'cam_optical')
    assert TF.static_frames('/base_link', 'cam_optical') == ('base_link', 'cam_optical')
    assert TF.static_frames('cam_optical', 'cam_optical') is None      # odometry tracks the optical frame
    assert TF.static_frames('', 'cam_optical') is None                 # no odometry child frame known yet
    assert TF.static_frames('base_link', '') is None
    assert TF.refined_frame('cam_optical') == 'cam_optical_refined'


class Diagnostics(dict):
    """The latest /diagnostics values of the node under test."""

    def __init__(self, node):
        from diagnostic_msgs.msg import DiagnosticArray
        super().__init__()
        node.create_subscription(DiagnosticArray, '/diagnostics', self._on, 10)

    def _on(self, msg):
        for status in msg.status:
            if status.name == 'dpv_sensor: depth camera':
                self.update({kv.key: kv.value for kv in status.values})


def _feed_one_image_and_odometry(node, executor, proc):
    """Publish one odometry (map -> base_link) and one image (frame cam_optical) to the node under test."""
    from nav_msgs.msg import Odometry
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image
    from dpv_sensor.ros import msgs as M
    from dpv_sensor.ros import pose_msgs as PM
    spin = lambda t: executor.spin_once(timeout_sec=t)  # noqa: E731
    qos = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE)
    pub_img = node.create_publisher(Image, '/image', qos)
    pub_odom = node.create_publisher(Odometry, '/odom', qos)
    assert wait_for(lambda: pub_img.get_subscription_count() == 1 and pub_odom.get_subscription_count() == 1,
                    timeout=60.0, spin=spin), 'the node never subscribed to its inputs'
    assert proc.poll() is None
    stamp = 1_700_000_000_000_000_000
    pub_odom.publish(PM.matrix_to_odometry(np.eye(4), stamp, 'base_link', frame_id='map'))
    pub_img.publish(M.rgb_to_image(np.zeros((8, 8, 3), np.uint8), M.make_header(stamp, 'cam_optical')))


def test_node_publishes_the_extrinsic_on_tf_static(observer):
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from tf2_msgs.msg import TFMessage
    node, executor = observer
    spin = lambda t: executor.spin_once(timeout_sec=t)  # noqa: E731
    proc = start_node(ros_args({**COMMON, 'publish_tf': True, 'T_base_camera': EXTRINSIC}))
    received = []
    diag = Diagnostics(node)
    try:
        _feed_one_image_and_odometry(node, executor, proc)
        assert wait_for(lambda: diag.get('tf', '').startswith('base_link -> cam_optical'), timeout=30.0, spin=spin), \
            diag
        # subscribe only now: the transform was published before, and a latched (transient local) one still arrives
        qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        node.create_subscription(TFMessage, '/tf_static', received.append, qos)
        assert wait_for(lambda: received, timeout=20.0, spin=spin), 'nothing arrived on /tf_static'
        info = node.get_publishers_info_by_topic('/tf_static')
    finally:
        code, out = stop_process(proc)
    assert code == 0, out
    assert [i.topic_type for i in info] == ['tf2_msgs/msg/TFMessage']
    assert str(info[0].topic_type_hash) == TFMESSAGE_HASH
    assert len(received[0].transforms) == 1
    tf = received[0].transforms[0]
    assert (tf.header.frame_id, tf.child_frame_id) == ('base_link', 'cam_optical')
    t, q = tf.transform.translation, tf.transform.rotation
    np.testing.assert_allclose([t.x, t.y, t.z, q.x, q.y, q.z, q.w], EXTRINSIC, atol=1e-12)
    np.testing.assert_allclose(make_pose([t.x, t.y, t.z], [q.x, q.y, q.z, q.w]),
                               make_pose(EXTRINSIC[:3], EXTRINSIC[3:]), atol=1e-12)


def test_publish_tf_false_publishes_no_tf(observer):
    node, executor = observer
    spin = lambda t: executor.spin_once(timeout_sec=t)  # noqa: E731
    diag = Diagnostics(node)
    proc = start_node(ros_args({**COMMON, 'publish_tf': False, 'T_base_camera': EXTRINSIC}))
    try:
        _feed_one_image_and_odometry(node, executor, proc)
        assert wait_for(lambda: diag.get('frames_received') == '1', timeout=30.0, spin=spin), diag
        tf_publishers = node.count_publishers('/tf_static') + node.count_publishers('/tf')
    finally:
        code, out = stop_process(proc)
    assert code == 0, out
    assert tf_publishers == 0 and diag['tf'] == 'off'
