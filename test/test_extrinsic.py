"""CameraExtrinsic (dpv_sensor.ros.extrinsic) on TF messages handed to its callbacks: which source auto picks, the
mount chained from /tf_static, a dynamic mount on /tf that changes (the next lookup uses the new one, one info line
per change), bad transforms ignored and counted."""
import collections
import math
from types import SimpleNamespace as NS

import numpy as np

from dpv_sensor import params as P
from dpv_sensor.ros.extrinsic import CameraExtrinsic
from dpv_sensor.ros.tf_publisher import tf_message, transform_stamped


class FakeNode:
    def __init__(self):
        self.callbacks = {}

    def create_subscription(self, _type, topic, callback, qos):
        self.callbacks[topic] = (callback, qos)
        return topic


class FakeFaults:
    def __init__(self):
        self.counts = collections.Counter()
        self.lines = []

    def report(self, kind, message, level='warn', count=True, **_):
        self.counts[kind] += count
        self.lines.append((level, message))


def translation(x, y, z):
    T = np.eye(4)
    T[:3, 3] = [x, y, z]
    return T


def test_auto_takes_the_parameter_unless_it_is_the_identity():
    assert P.extrinsic_source('auto', P.IDENTITY_POSE) == 'tf'
    assert P.extrinsic_source('auto', [0.0, 0.0, 0.1, 0.0, 0.0, 0.0, 1.0]) == 'parameter'
    assert P.extrinsic_source('auto', [0.0, 0.0, 0.0, 0.0, 0.0, math.sqrt(0.5), math.sqrt(0.5)]) == 'parameter'
    assert P.extrinsic_source('parameter', P.IDENTITY_POSE) == 'parameter'
    assert P.extrinsic_source('tf', [0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]) == 'tf'


def test_parameter_source_subscribes_nothing():
    node = FakeNode()
    ext = CameraExtrinsic(node, FakeFaults(), 'parameter', 'auto', translation(0.0, 0.0, 0.3))
    assert node.callbacks == {}
    T, why = ext.lookup('base_link', 'cam')
    np.testing.assert_allclose(T, translation(0.0, 0.0, 0.3))
    assert why == ''
    assert ext.values()['extrinsic_source'] == 'parameter (auto)'


def test_mount_from_tf_static_and_a_changing_dynamic_mount():
    from rclpy.qos import DurabilityPolicy, ReliabilityPolicy
    node, faults, woken = FakeNode(), FakeFaults(), []
    ext = CameraExtrinsic(node, faults, 'tf', 'tf', np.eye(4), on_update=lambda: woken.append(1))
    static_cb, static_qos = node.callbacks['/tf_static']
    dynamic_cb, dynamic_qos = node.callbacks['/tf']
    assert (static_qos.durability, static_qos.reliability, static_qos.depth) == \
        (DurabilityPolicy.TRANSIENT_LOCAL, ReliabilityPolicy.RELIABLE, 100)
    assert dynamic_qos.durability == DurabilityPolicy.VOLATILE
    T, why = ext.lookup('base_link', 'cam')
    assert T is None and "'base_link'" in why and ext.values()['extrinsic'].startswith('waiting for TF')
    assert ext.lookup('', 'cam')[1].startswith('the odometry has no child_frame_id')

    static_cb(tf_message([transform_stamped(translation(0.2, 0.0, 0.5), 0, 'base_link', 'camera_link')]))
    dynamic_cb(tf_message([transform_stamped(translation(0.0, 0.1, 0.0), 0, 'camera_link', 'cam')]))
    assert woken == [1, 1]
    T, _ = ext.lookup('base_link', 'cam')
    np.testing.assert_allclose(T[:3, 3], [0.2, 0.1, 0.5])
    ext.lookup('base_link', 'cam')                                    # the same mount: no second line
    assert [m for lvl, m in faults.lines if lvl == 'info'] == [
        "camera mount from TF: 'base_link' -> 'cam' xyz [0.200, 0.100, 0.500] q [0.0000, 0.0000, 0.0000, 1.0000]; "
        'used for the following images']
    dynamic_cb(tf_message([transform_stamped(translation(0.0, -0.1, 0.0), 0, 'camera_link', 'cam')]))
    T, _ = ext.lookup('base_link', 'cam')
    np.testing.assert_allclose(T[:3, 3], [0.2, -0.1, 0.5])
    assert ext.changes == 1 and ext.values()['extrinsic_changes'] == 1
    assert faults.lines[-1][0] == 'info' and faults.lines[-1][1].startswith('camera mount changed on TF')

    bad = transform_stamped(translation(0.0, 0.0, 0.0), 0, 'camera_link', 'cam')
    bad.transform.rotation = NS(x=0.0, y=0.0, z=0.0, w=2.0)
    dynamic_cb(tf_message([bad]))
    assert faults.counts['bad_transform'] == 1 and 'not a unit quaternion' in faults.lines[-1][1]
    np.testing.assert_allclose(ext.lookup('base_link', 'cam')[0][:3, 3], [0.2, -0.1, 0.5])   # kept the last good
