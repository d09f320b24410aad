"""CameraExtrinsic (dpv_sensor.ros.extrinsic) on TF messages handed to its callbacks: which source auto picks, the
mount chained from /tf_static, a dynamic mount on /tf that changes (the next lookup uses the new one, one info line
per change; a turn without a move is a change), bad transforms ignored and counted; a loop through the mount's path
and publishers that disagree on it (the last good mount kept, counted, a WARN naming the frames, extrinsic_fault)."""
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

    def count(self, kind, n=1):
        self.counts[kind] += n


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


def rotation(axis, rad):
    """Rodrigues: the rotation by `rad` about `axis`."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(rad) * K + (1.0 - math.cos(rad)) * K @ K


def rigid(R, t):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


MOUNT_T = (0.3, -0.4, 1.2)                         # 1.3 m: not a unit length
MOUNT_R = rotation((1.0, 2.0, 2.0), 0.4)


def tf_extrinsic():
    node, faults = FakeNode(), FakeFaults()
    ext = CameraExtrinsic(node, faults, 'tf', 'tf', np.eye(4))
    return ext, faults, node.callbacks['/tf_static'][0], node.callbacks['/tf'][0]


def infos(faults):
    return [m for lvl, m in faults.lines if lvl == 'info']


def test_a_mount_that_turns_without_moving_is_reported_as_changed():
    ext, faults, _static, dynamic = tf_extrinsic()
    dynamic(tf_message([transform_stamped(rigid(MOUNT_R, MOUNT_T), 0, 'base_link', 'cam')]))
    ext.lookup('base_link', 'cam')
    turned = MOUNT_R @ rotation((0.0, 0.0, 1.0), 3e-6)                 # 3 microradians, the translation kept
    dynamic(tf_message([transform_stamped(rigid(turned, MOUNT_T), 0, 'base_link', 'cam')]))
    T, _ = ext.lookup('base_link', 'cam')
    np.testing.assert_allclose(T[:3, :3], turned, atol=1e-12)
    assert ext.changes == 1 and infos(faults)[-1].startswith("camera mount changed on TF: 'base_link' -> 'cam'")
    less = turned @ rotation((0.0, 0.0, 1.0), 0.5e-6)                  # below the 1e-6 threshold: the same mount
    dynamic(tf_message([transform_stamped(rigid(less, MOUNT_T), 0, 'base_link', 'cam')]))
    ext.lookup('base_link', 'cam')
    assert ext.changes == 1 and len(infos(faults)) == 2


CLOSING = rigid(rotation((0.0, 0.0, 1.0), math.radians(30.0)), (0.5, 0.1, 0.0))   # cam -> base_link: a loop
LOOP = "'base_link' -> 'camera_link' -> 'cam' -> 'base_link'"


def _chain(static):
    static(tf_message([transform_stamped(rigid(MOUNT_R, MOUNT_T), 0, 'base_link', 'camera_link'),
                       transform_stamped(rigid(MOUNT_R.T, (0.0, 0.1, 0.0)), 0, 'camera_link', 'cam')]))


def test_a_tf_loop_keeps_the_last_good_mount_counts_once_and_warns_naming_the_frames():
    ext, faults, static, _dynamic = tf_extrinsic()
    _chain(static)
    good, _ = ext.lookup('base_link', 'cam')
    np.testing.assert_allclose(good, rigid(np.eye(3), MOUNT_R @ [0.0, 0.1, 0.0] + MOUNT_T), atol=1e-12)
    assert ext.values()['extrinsic_fault'] == ''
    static(tf_message([transform_stamped(CLOSING, 0, 'cam', 'base_link')]))      # another publisher closes it
    for _ in range(3):
        T, why = ext.lookup('base_link', 'cam')
        np.testing.assert_allclose(T, good, atol=1e-12)
        assert why == ''
    assert faults.counts['tf_loop'] == 1 and ext.changes == 0 and len(infos(faults)) == 1     # the first mount
    level, message = faults.lines[-1]
    assert level == 'warn' and message.startswith(f"TF loop on the camera mount's path 'base_link' -> 'cam': {LOOP}")
    assert 'keeping the last good mount xyz' in message
    assert ext.values()['extrinsic_fault'] == f'TF loop on the camera mount path: {LOOP}'
    # with the loop there from the start there is no good mount: none, and why
    fresh, fresh_faults, fresh_static, _ = tf_extrinsic()
    _chain(fresh_static)
    fresh_static(tf_message([transform_stamped(CLOSING, 0, 'cam', 'base_link')]))
    assert fresh.lookup('base_link', 'cam') == (None, f'a loop in TF: {LOOP}')
    assert fresh_faults.counts['tf_loop'] == 1 and 'no good mount yet' in fresh_faults.lines[-1][1]


def test_static_publishers_that_disagree_hold_the_mount_count_each_message_and_warn():
    """Two latched publishers of camera_link -> cam that differ in rotation only (the translation, 1.3 m, kept)."""
    ext, faults, static, _dynamic = tf_extrinsic()
    static(tf_message([transform_stamped(rigid(np.eye(3), (0.2, 0.0, 0.5)), 0, 'base_link', 'camera_link')]))
    first, other = rigid(MOUNT_R, MOUNT_T), rigid(MOUNT_R @ rotation((0.0, 1.0, 0.0), 0.05), MOUNT_T)
    seen = []
    for T in (first, other, first, other, first, other):
        static(tf_message([transform_stamped(T, 0, 'camera_link', 'cam')]))
        seen.append(ext.lookup('base_link', 'cam')[0])
    for T in seen:
        np.testing.assert_allclose(T[:3, :3], MOUNT_R, atol=1e-12)      # always the first publisher's turn
    assert faults.counts['tf_mount_flip'] == 5 and faults.counts['tf_conflicting_parents'] == 0
    assert ext.changes == 0 and len(infos(faults)) == 1                  # no 'changed' line per flip
    warn = [m for lvl, m in faults.lines if lvl == 'warn']
    assert warn[0].startswith("TF on the camera mount's path 'base_link' -> 'cam': /tf_static publishers disagree "
                              "on 'camera_link' -> 'cam': xyz [0.300, -0.400, 1.200]"), warn
    assert ext.values()['extrinsic_fault'] == ("TF publishers disagree on the camera mount path: 'camera_link' -> "
                                               "'cam' (transforms, held)")
    for T in (first, other, first):                 # three more between two images: counted as they arrive
        static(tf_message([transform_stamped(T, 0, 'camera_link', 'cam')]))
    assert faults.counts['tf_mount_flip'] == 8
    ext.lookup('base_link', 'cam')
    assert faults.counts['tf_mount_flip'] == 8      # not again at the next image


def test_a_second_parent_on_tf_is_a_conflicting_parent_and_the_static_one_stays():
    ext, faults, static, dynamic = tf_extrinsic()
    _chain(static)
    good, _ = ext.lookup('base_link', 'cam')
    dynamic(tf_message([transform_stamped(translation(1.0, 0.0, 0.0), 0, 'odom', 'camera_link')]))
    T, _ = ext.lookup('base_link', 'cam')
    np.testing.assert_allclose(T, good, atol=1e-12)
    assert faults.counts['tf_conflicting_parents'] == 1 and faults.counts['tf_mount_flip'] == 0
    assert "frame 'camera_link' is given conflicting parents 'base_link', 'odom'" in faults.lines[-1][1]
    assert ext.values()['extrinsic_fault'].endswith("'base_link' -> 'camera_link' (parents, held)")
