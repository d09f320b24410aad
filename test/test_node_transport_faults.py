"""Faults a robot's camera and odometry produce, through the node process at its default input QoS: a burst of images
from a reliable publisher whose history overflows (every image is accounted for: received + lost = sent, from the
publication sequence numbers, with no stamp jump and no ERROR once the stream is clean again), a second camera on the
image topic (warned about, counted, never fused), and odometry later than odom_wait_timeout (the images it holds up
are counted under the odometry, not as a busy estimator)."""
import time

import cv2

from ros_helpers import wait_for
from stream_driver import FAST_PARAMS, H, W, StreamDriver, params_args
from dpv_sensor.ros import msgs as M
from dpv_sensor.ros import pose_msgs as PM
from dpv_sensor.stream.pose_buffer import NS

REMAPS = {'image': '/cam/image', 'camera_info': '/cam/camera_info', 'odom': '/odom'}
P30 = NS // 30
# the estimator at the test's size, the node's input QoS at its defaults (input_depth 5)
PARAMS = {k: v for k, v in FAST_PARAMS.items() if k != 'input_depth'}


def _send_big(drv: StreamDriver, i: int, stamp_ns: int, size=(640, 480)) -> None:
    """Odometry, camera_info and a 640x480 image (the rendered frame scaled up) at `stamp_ns`."""
    k = i % len(drv.seq)
    drv.send_odom(k, stamp_ns)
    drv.pubs['camera_info'].publish(M.K_to_camera_info(M.scale_K(drv.seq.K, (W, H), size), size[0], size[1],
                                                       stamp_ns, 'cam'))
    rgb = cv2.resize(drv.seq.image(k), size, interpolation=cv2.INTER_LINEAR)
    drv.pubs['image'].publish(M.rgb_to_image(rgb, stamp_ns, 'cam'))


def _burst(drv: StreamDriver, sent: int, t: int, n: int, lead_in: int) -> tuple:
    """`lead_in` images at 30 Hz, `n` back to back (stamps 1/30 s apart), then 14 at 4 Hz (the stream is clean
    again); returns (sent, last stamp)."""
    for _ in range(lead_in):
        t += P30
        _send_big(drv, sent, t)
        sent += 1
        drv.spin(1 / 30)
    for _ in range(n):
        t += P30
        _send_big(drv, sent, t)
        sent += 1
    for _ in range(14):
        t += P30
        _send_big(drv, sent, t)
        sent += 1
        end = time.monotonic() + 0.25
        while time.monotonic() < end:
            drv.spin(0.02)
    return sent, t


def test_a_burst_from_a_reliable_publisher_is_accounted_for_image_by_image():
    # a reliable publisher keeping the last 5 samples: 200 images of 640x480 back to back usually overflow it (and
    # the node's 5-deep reader history); the samples it drops are reported by no lost-event. Whether a burst
    # overflows depends on how fast the node's reader drains it on this machine at this moment: a burst that did not
    # is followed by a longer one (received + lost = sent is checked after each), until one did
    drv = StreamDriver(params_args(PARAMS, REMAPS), topics=REMAPS, frames=20, name='burst_sequence', depth=5)
    sent, t = 0, drv.stamp_ns(0)
    bursts = []
    try:
        drv.wait_ready()
        for n in (200, 400, 800):
            sent, t = _burst(drv, sent, t, n, lead_in=30 if not bursts else 0)
            arrived = lambda: drv.diag('frames_received') + drv.diag('lost.transport') >= sent  # noqa: E731
            assert wait_for(arrived, timeout=30.0, spin=drv.spin), drv.outputs.diagnostics
            assert drv.wait_accounted(drv.diag('frames_received'), timeout=60.0), drv.outputs.diagnostics
            diag = drv.wait_diagnostics()
            received, lost = int(diag['frames_received']), int(diag['lost.transport'])
            bursts.append((n, sent, received, lost))
            assert received + lost == sent, (bursts, diag)
            if lost > 0:
                break
        level, message = drv.outputs.diagnostics_level, drv.outputs.diagnostics_message
    finally:
        log = drv.stop()
    assert drv.code == 0, log
    print(f'bursts (size, sent, received, lost): {bursts}; sequence gaps only '
          f"{diag.get('lost.sequence_gaps_only')}, stamp gaps only {diag['lost.stamp_gaps_only']}, "
          f"reported {diag['lost.rmw']}, dropped {diag['dropped_total']}")
    assert lost > 0, bursts                                  # a burst did overflow a history
    assert int(diag['input_stamp_jumps']) == 0 and 'faults.stamp_jump' not in diag, diag
    assert 'image stamps jumped' not in log, log
    assert level != 2, (level, message)                      # no ERROR about a fault that is over
    assert 'over' in message or level == 0, (level, message)


def test_a_second_camera_on_the_image_topic_is_dropped_counted_and_never_published():
    drv = StreamDriver(params_args(PARAMS, REMAPS), topics=REMAPS, frames=20, name='two_cameras')
    sent = 0
    try:
        drv.wait_ready()
        for i in range(30):                  # 'cam' at 30 Hz (with its odometry), 'cam_b' at 10 Hz in between
            drv.send(i, drv.stamp_ns(i))
            sent += 1
            if i % 3 == 1:
                drv.pubs['image'].publish(M.rgb_to_image(drv.seq.image((i + 7) % len(drv.seq)),
                                                         drv.stamp_ns(i) + P30 // 2, 'cam_b'))
                sent += 1
            assert drv.wait_accounted(sent), drv.outputs.diagnostics
        assert wait_for(lambda: drv.outputs.depth_count > 0, timeout=30.0, spin=drv.spin)
        diag = drv.wait_diagnostics()
        frames = {rec.frame_id for rec in drv.outputs.by_stamp.values()}
    finally:
        log = drv.stop()
    assert drv.code == 0, log
    assert int(diag['dropped.other_camera']) == 10 and int(diag['faults.other_camera']) == 10, diag
    assert int(diag['frames_received']) == sent and int(diag['lost.transport']) == 0, diag
    assert frames == {'cam'}, frames
    warn = [line for line in log.splitlines() if 'two cameras publish on one image topic' in line]
    assert warn and "'cam_b'" in warn[0] and "'cam'" in warn[0] and 'Remap one of them' in warn[0], log


def test_odometry_later_than_the_wait_timeout_drops_images_under_the_odometry_not_busy():
    drv = StreamDriver(params_args({**PARAMS, 'odom_wait_timeout': 0.5}, REMAPS), topics=REMAPS, frames=20,
                       name='late_odometry')
    n, late = 45, 21                         # odometry 0.7 s after its image: 21 frames at 30 Hz
    try:
        drv.wait_ready()
        start = time.monotonic()
        for i in range(n + late):
            while time.monotonic() < start + i / 30:
                drv.spin(0.005)
            if i < n:
                stamp = drv.stamp_ns(i)
                drv.pubs['camera_info'].publish(M.K_to_camera_info(drv.seq.K, W, H, stamp, 'cam'))
                drv.pubs['image'].publish(M.rgb_to_image(drv.seq.image(i % len(drv.seq)), stamp, 'cam'))
            if i >= late:
                drv.send_odom(i - late, drv.stamp_ns(i - late))
        assert drv.wait_accounted(n, timeout=30.0), drv.outputs.diagnostics
        diag = drv.wait_diagnostics()
    finally:
        log = drv.stop()
    assert drv.code == 0, log
    timeout, held_up = int(diag.get('dropped.odometry_timeout', 0)), int(diag.get('dropped.odometry_late', 0))
    busy = int(diag.get('dropped.busy', 0))
    print(f'late odometry: {n} images, odometry_timeout {timeout}, odometry_late {held_up}, busy {busy}, '
          f"processed {diag['frames_processed']}")
    assert int(diag['frames_received']) == n, diag
    assert timeout + held_up >= n - 3 and held_up > timeout, diag      # nearly all held up by the odometry ...
    assert busy <= 2, diag                                             # ... and not a busy estimator
    assert 'odometry arrives later than the images' in log, log


def test_odometry_with_a_nan_covariance_or_a_zero_stamp_is_a_fault_of_its_own():
    drv = StreamDriver(params_args(PARAMS, REMAPS), topics=REMAPS, frames=20, name='odometry_faults')
    try:
        drv.wait_ready()
        for i in range(12):
            stamp = drv.stamp_ns(i)
            if i == 4:                       # its odometry first, with NaN in the pose covariance
                odom = PM.matrix_to_odometry(drv.seq.pose(i), stamp, 'base_link', 'odom', position_sigma=0.01,
                                            rotation_sigma=0.01)
                cov = list(odom.pose.covariance)
                cov[7] = float('nan')
                odom.pose.covariance = cov
                drv.pubs['odom'].publish(odom)
            if i == 7:                       # an unstamped odometry message
                drv.pubs['odom'].publish(PM.matrix_to_odometry(drv.seq.pose(i), 0, 'base_link', 'odom'))
            drv.send(i, stamp)
            assert drv.wait_accounted(i + 1), drv.outputs.diagnostics
        diag = drv.wait_diagnostics()
    finally:
        log = drv.stop()
    assert drv.code == 0, log
    assert int(diag['faults.odometry_covariance_nan']) == 1, diag
    assert int(diag['faults.odometry_zero_stamp']) == 1, diag
    assert 'faults.time_backwards' not in diag and 'faults.odometry_conflict' not in diag, diag
    assert 'NaN or infinity in its pose covariance: the covariance is ignored' in log, log
    assert 'odometry header.stamp is zero: the driver does not stamp its messages' in log, log
    assert 'bag restarted' not in log and 'two odometry sources' not in log, log


def test_under_sim_time_without_clock_the_inputs_follow_their_publishers_and_no_stamp_age_is_made_up():
    # no /clock is published: ROS time stays 0; the stamps are a simulator's (100 s on)
    drv = StreamDriver(params_args({**PARAMS, 'use_sim_time': True}, REMAPS), topics=REMAPS, frames=20,
                       name='sim_time')
    try:
        drv.wait_ready()                     # input_reliability auto re-subscribed reliable without /clock
        for i in range(8):
            drv.send(i, 100 * NS + i * P30)
            assert drv.wait_accounted(i + 1), drv.outputs.diagnostics
        assert wait_for(lambda: drv.outputs.depth_count > 0, timeout=30.0, spin=drv.spin)
        diag = drv.wait_diagnostics()
    finally:
        log = drv.stop()
    assert drv.code == 0, log
    assert diag['stamp_age_ms_median'] == 'n/a' and diag['stamp_age_clock'] == 'sim time', diag
    assert int(diag['stamp_age_implausible']) == int(diag['outputs_published']) >= 1, diag
