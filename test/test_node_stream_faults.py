"""Stream faults through the node process: a camera that lowers its rate, stamps that jump an hour ahead, odometry
that changes its frame_id, and a burst with truncated images arriving while the worker is busy followed by a slow
clean stream. Losses are counted only on evidence (no image is lost here, so none may be counted), a stamp jump is
a discontinuity with a warning, and a bad image is counted and logged on receipt even when the worker never sees it.
"""
import re

from ros_helpers import wait_for
from stream_driver import FAST_PARAMS, ONE_AT_A_TIME, StreamDriver, params_args
from dpv_sensor.stream.pose_buffer import NS

P30 = NS // 30
REMAPS = {'image': '/cam/image', 'camera_info': '/cam/camera_info', 'odom': '/odom'}


def _driver(name: str, **params) -> StreamDriver:
    return StreamDriver(params_args({**FAST_PARAMS, **params}, REMAPS), topics=REMAPS, frames=40, name=name,
                        depth=300)


def test_rate_drops_and_a_stamp_jump_lose_nothing_and_a_frame_id_change_is_reported():
    drv = _driver('rate_faults', **ONE_AT_A_TIME)
    phases = [('30 Hz', P30, 30, 'odom'), ('15 Hz', 2 * P30, 30, 'odom'), ('4 Hz', NS // 4, 20, 'odom'),
              ('1 h ahead', P30, 30, 'odom'), ('map frame', P30, 15, 'map')]
    sent = 0
    t = drv.stamp_ns(0)
    try:
        drv.wait_ready()
        for label, period, n, frame in phases:
            if label == '1 h ahead':
                t += 3600 * NS
            for _ in range(n):
                t += period
                drv.send(sent, t, odom_frame=frame)
                sent += 1
                assert drv.wait_accounted(sent), (label, drv.outputs.diagnostics)
        diag = drv.wait_diagnostics()
    finally:
        log = drv.stop()
    assert drv.code == 0, log
    assert int(diag['frames_received']) == sent, diag
    assert int(diag['lost.transport']) == 0, diag                # every image arrived: none counted lost
    assert int(diag['input_rate_changes']) >= 2, diag            # 30 -> 15 -> 4 Hz, re-estimated each time
    assert int(diag['input_stamp_jumps']) == 1 and int(diag['faults.stamp_jump']) == 1, diag
    assert re.search(r'image stamps jumped 3600\.\d+ s forward', log), log
    assert int(diag['faults.odometry_frame_change']) == 1, diag
    assert log.count("odometry frame_id changed from 'odom' to 'map'") == 1, log
    assert float(diag['drop_share_window']) < 0.5, diag
    assert drv.outputs.depth_count > 0


def test_bad_images_in_a_burst_are_counted_on_receipt_and_a_slow_stream_after_it_loses_nothing():
    drv = _driver('burst_faults', input_depth=300)
    burst, bad_every = 150, 10
    t = drv.stamp_ns(0)
    try:
        drv.wait_ready()
        bad = 0
        for i in range(burst):               # as fast as the client publishes: the worker is busy for most
            t += P30
            msg = None
            if i % bad_every == 5:
                from dpv_sensor.ros import msgs as M
                msg = M.rgb_to_image(drv.seq.image(i % len(drv.seq)), t, 'cam')
                msg.data = msg.data[:len(msg.data) // 2]          # truncated
                bad += 1
            drv.send(i, t, image_msg=msg)
        assert drv.wait_accounted(burst, timeout=90.0), drv.outputs.diagnostics
        after_burst = drv.wait_diagnostics()
        for i in range(burst, burst + 20):   # then a clean 4 Hz stream, one image at a time
            t += NS // 4
            drv.send(i, t)
            assert drv.wait_accounted(i + 1), drv.outputs.diagnostics
        diag = drv.wait_diagnostics()
    finally:
        log = drv.stop()
    assert drv.code == 0, log
    assert int(diag['frames_received']) == burst + 20, diag     # reliable and deep enough: nothing lost
    assert int(diag['dropped.bad_image']) == bad, diag          # every one, although most arrived while busy
    assert int(after_burst.get('dropped.busy', 0)) > 0, after_burst
    assert len(re.findall(r'dropping image at [\d.]+ s: .*data length', log)) >= 1, log
    assert int(diag['lost.transport']) == int(after_burst['lost.transport']) == 0, diag


def test_stamps_far_off_the_node_clock_report_no_stamp_age():
    """A bag written from a folder without stamps starts at stamp 0: its age on the node's clock (56 years) is no
    latency, so none is reported and the outputs are counted in stamp_age_implausible."""
    drv = _driver('stamp_age')
    try:
        drv.wait_ready()
        for i in range(8):
            drv.send(i, (i + 1) * P30)
            assert drv.wait_accounted(i + 1), drv.outputs.diagnostics
        assert wait_for(lambda: drv.outputs.depth_count > 0, timeout=30.0, spin=drv.spin)
        diag = drv.wait_diagnostics()
    finally:
        log = drv.stop()
    assert drv.code == 0, log
    assert diag['stamp_age_ms_median'] == 'n/a', diag
    assert int(diag['stamp_age_implausible']) == int(diag['outputs_published']) >= 1, diag


def test_a_lens_cap_with_sensor_noise_and_a_nearly_saturated_frame_are_dropped_as_degenerate():
    import numpy as np
    from stream_driver import H, W, lens_cap
    rng = np.random.default_rng(0)
    cap = np.clip(lens_cap(rng, 4, 2.0), 0, 10)                                        # covered lens, dark noise
    glare = np.clip(rng.normal(253, 1.5, (H, W, 3)), 250, 255).astype(np.uint8)       # overexposed, clipping
    drv = _driver('degenerate_noise')
    frames = {6: cap, 7: cap, 9: glare}          # two episodes: a textured frame between them
    try:
        drv.wait_ready()
        for i in range(12):
            drv.send(i, drv.stamp_ns(i), image=frames.get(i))
            assert drv.wait_accounted(i + 1), drv.outputs.diagnostics
        diag = drv.wait_diagnostics()
        published = set(drv.outputs.by_stamp)
    finally:
        log = drv.stop()
    assert drv.code == 0, log
    assert int(diag['dropped.degenerate_image']) == 3, diag
    assert not {drv.stamp_ns(i) for i in frames} & published
    assert 'degenerate images from' in log and '(black' in log and '(saturated' in log, log
