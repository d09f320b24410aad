"""Every drop counted by its true cause, through the node process: images replaced in the mailbox while the worker
waits for the pose of the image before them count by how that wait ended: the camera mount not on TF yet
(dropped.no_extrinsic, not busy), odometry that never came within odom_wait_timeout (dropped.odometry_late), odometry
that came but with a gap around the image (dropped.busy: the odometry was not late). An image stamped ahead of the
node's clock and the odometry by more than future_stamp_tolerance is dropped at once as dropped.future_stamp with its
own words; one just under the tolerance, or ahead of the clock but not of the odometry, is waited for as usual
(odometry_timeout).

Stamps are on the node's clock (the system clock): the images run a minute behind it, and the future ones are
stamped from the clock at the moment they are sent. The client waits for the node to be waiting for a pose
(/diagnostics waiting_for_pose) before it sends the images to be replaced meanwhile, so the counts are exact."""
import time

import numpy as np

from ros_helpers import wait_for
from stream_driver import FAST_PARAMS, H, W, StreamDriver, params_args
from dpv_sensor.ros import msgs as M
from dpv_sensor.ros.fault_kinds import BUSY, NO_EXTRINSIC, ODOM_LATE
from dpv_sensor.ros.inputs import NO_MOUNT, replaced_drop_kind
from dpv_sensor.stream.pose_buffer import FUTURE, GAP, NAN, NS, TOO_OLD

WAIT_S = 2.0             # odom_wait_timeout: long enough to send two images while the worker waits, under load
TOLERANCE_S = 1.0        # future_stamp_tolerance
P30 = NS // 30


def test_images_replaced_during_a_wait_count_by_how_the_wait_ended():
    assert replaced_drop_kind(FUTURE) == ODOM_LATE          # the odometry never came in time
    assert replaced_drop_kind(NO_MOUNT) == NO_EXTRINSIC     # the camera mount was not on TF
    for reason in (GAP, TOO_OLD, NAN, None):                # the odometry came (and failed), or the pose did
        assert replaced_drop_kind(reason) == BUSY, reason


class Client:
    """The driver's images on stamps a minute behind the system clock (the node's), one counter of sent images."""

    def __init__(self, drv: StreamDriver):
        self.drv = drv
        self.base_ns = time.time_ns() - 60 * NS
        self.sent = 0

    def stamp(self, k: float) -> int:
        return self.base_ns + int(k * P30)

    def image(self, stamp_ns: int, odometry: bool = True) -> None:
        """An image (with its camera_info, and its odometry unless `odometry` is False) at `stamp_ns`."""
        drv, k = self.drv, self.sent % len(self.drv.seq)
        if odometry:
            drv.send(k, stamp_ns)
        else:
            drv.pubs['camera_info'].publish(M.K_to_camera_info(drv.seq.K, W, H, stamp_ns, 'cam'))
            drv.pubs['image'].publish(M.rgb_to_image(drv.seq.image(k), stamp_ns, 'cam'))
        self.sent += 1

    def counts(self) -> dict:
        diag = self.drv.wait_diagnostics()
        return {k: int(v) for k, v in diag.items() if k.startswith(('dropped.', 'faults.', 'frames_'))}

    def wait_waiting(self) -> None:
        """Until /diagnostics says the worker waits for a pose (the image it took is in the wait)."""
        assert wait_for(lambda: self.drv.outputs.diagnostics.get('waiting_for_pose') == 'True', timeout=20.0,
                        spin=self.drv.spin), self.drv.outputs.diagnostics

    def odometry(self, stamp_ns: int) -> None:
        """Odometry at `stamp_ns`, waited for until the node has taken it (/diagnostics odometry_received): it and the
        image after it come on two topics, so the image could otherwise be judged before the odometry is there."""
        before = int(self.drv.wait_diagnostics()['odometry_received'])     # fresh: all sent before it is taken
        self.drv.send_odom(0, stamp_ns)
        assert wait_for(lambda: self.drv.diag('odometry_received') > before, timeout=20.0, spin=self.drv.spin), \
            self.drv.outputs.diagnostics

    def wait_received(self) -> None:
        assert wait_for(lambda: self.drv.diag('frames_received') >= self.sent, timeout=20.0, spin=self.drv.spin), \
            self.drv.outputs.diagnostics

    def wait_accounted(self) -> None:
        assert self.drv.wait_accounted(self.sent, timeout=60.0), self.drv.outputs.diagnostics


def delta(after: dict, before: dict) -> dict:
    return {k: v - before.get(k, 0) for k, v in after.items() if v != before.get(k, 0)}


def _publish_mount(drv: StreamDriver):
    """base_link -> cam (identity) on /tf_static, latched."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from tf2_msgs.msg import TFMessage
    from dpv_sensor.ros.tf_publisher import tf_message, transform_stamped
    qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    pub = drv.node.create_publisher(TFMessage, '/tf_static', qos)
    assert wait_for(lambda: pub.get_subscription_count() >= 1, timeout=20.0, spin=drv.spin)
    pub.publish(tf_message([transform_stamped(np.eye(4), 0, 'base_link', 'cam')]))
    return pub


def test_drops_while_waiting_count_as_the_mount_late_odometry_or_busy_and_future_stamps_as_their_own():
    params = {**FAST_PARAMS, 'pose_refinement': 'off', 'extrinsic_source': 'auto', 'odom_wait_timeout': WAIT_S,
              'max_odom_gap': 0.5, 'future_stamp_tolerance': TOLERANCE_S}
    drv = StreamDriver(params_args(params), frames=12, name='drop_causes')
    c = Client(drv)
    steps = {}
    try:
        drv.wait_ready()
        # 1. no mount on TF: the image the worker waits with, the one replaced meanwhile and the one after it all
        #    count as waiting for the mount
        before = c.counts()
        c.image(c.stamp(0))
        c.wait_waiting()
        c.image(c.stamp(1))
        c.image(c.stamp(2))
        c.wait_received()
        c.wait_accounted()
        steps['no mount'] = delta(c.counts(), before)
        pub = _publish_mount(drv)
        for k in range(3, 7):
            c.image(c.stamp(k))
            c.wait_accounted()
        # 2. the odometry stops before image 7; images 8 and 9 arrive while the worker waits; then odometry 1 s
        #    later comes: a gap around 7 and 9. The odometry was not late: 8 is a busy drop
        before = c.counts()
        c.image(c.stamp(7), odometry=False)
        c.wait_waiting()
        c.image(c.stamp(8), odometry=False)
        c.image(c.stamp(9), odometry=False)
        c.wait_received()
        drv.send_odom(0, c.stamp(7) + NS)
        c.wait_accounted()
        steps['gap'] = delta(c.counts(), before)
        # 3. the same, but no odometry comes: 10 and 12 time out, 11 was held up by the late odometry
        before = c.counts()
        c.image(c.stamp(40), odometry=False)
        c.wait_waiting()
        c.image(c.stamp(41), odometry=False)
        c.image(c.stamp(42), odometry=False)
        c.wait_received()
        c.wait_accounted()
        steps['late'] = delta(c.counts(), before)
        for k in range(43, 46):              # the odometry is back
            c.image(c.stamp(k))
            c.wait_accounted()
        # 4. stamps ahead of the clock (and far ahead of the odometry): just under the tolerance, waited for (it
        #    times out: no odometry comes); over it, dropped at once as a future stamp
        before = c.counts()
        c.image(time.time_ns() + int((TOLERANCE_S - 0.3) * NS), odometry=False)
        c.wait_accounted()
        steps['under the tolerance'] = delta(c.counts(), before)
        # ahead of the clock by more than the tolerance, but not of the odometry (its clock runs ahead too): waited
        # for as usual
        before = c.counts()
        now = time.time_ns()
        c.odometry(now + 3 * NS)
        assert time.time_ns() < now + int((3.5 - TOLERANCE_S) * NS), 'too slow to test a stamp ahead of the clock'
        c.image(now + int(3.5 * NS), odometry=False)
        c.wait_accounted()
        steps['ahead of the clock, not of the odometry'] = delta(c.counts(), before)
        before = c.counts()
        sent = time.monotonic()
        c.image(time.time_ns() + int((TOLERANCE_S + 0.6) * NS), odometry=False)
        c.wait_accounted()
        took = time.monotonic() - sent
        steps['over the tolerance'] = delta(c.counts(), before)
        final = drv.wait_diagnostics()
        del pub
    finally:
        log = drv.stop()
    assert drv.code == 0, log
    print('drops by step:', steps)
    assert steps['no mount'] == {'dropped.no_extrinsic': 3, 'faults.no_extrinsic': 2, 'frames_received': 3}, steps
    assert steps['gap'] == {'dropped.odometry_gap': 2, 'faults.odometry_gap': 2, 'dropped.busy': 1,
                            'frames_received': 3}, steps
    late = steps['late']
    assert late['dropped.odometry_timeout'] == 2 and late['dropped.odometry_late'] == 1, steps
    assert 'dropped.busy' not in late and 'dropped.future_stamp' not in late, steps
    assert steps['under the tolerance'].get('dropped.odometry_timeout') == 1, steps
    assert 'dropped.future_stamp' not in steps['under the tolerance'], steps
    assert steps['ahead of the clock, not of the odometry'].get('dropped.odometry_timeout') == 1, steps
    assert 'dropped.future_stamp' not in steps['ahead of the clock, not of the odometry'], steps
    assert steps['over the tolerance'].get('dropped.future_stamp') == 1, steps
    assert steps['over the tolerance'].get('faults.future_stamp') == 1, steps
    assert 'dropped.odometry_timeout' not in steps['over the tolerance'], steps
    assert took < WAIT_S, f'the future image was waited for ({took:.1f} s)'
    assert int(final['frames_received']) == c.sent == int(final['frames_processed']) + int(final['dropped_total'])
    future = [line for line in log.splitlines() if 'dropped.future_stamp' in line]
    assert len(future) == 1 and 'WARN' in future[0] and "ahead of the node's clock" in future[0], log
    assert 'more than future_stamp_tolerance 1 s' in future[0] and 'odometry arrives later' not in future[0], log
    assert log.count('odometry arrives later than the images') == 1, log          # the late step's only
