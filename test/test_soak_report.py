"""The soak report's memory trend: medians per window, so a leak shows as a climb and a plateau as a plateau."""
from dpv_sensor.tools.soak import rss_trend


def test_rss_trend_windows_and_medians():
    # 30 min, a sample every 10 s: 1000 MB rising 1 MB per minute for the first 10 min, then flat at 1010
    samples = [(t, 1000 * 1024 + min(t, 600.0) / 60.0 * 1024) for t in range(0, 1800, 10)]
    trend = rss_trend(samples, 1800.0)
    assert [(a, b) for a, b, _ in trend] == [(0.0, 300.0), (300.0, 600.0), (600.0, 900.0), (900.0, 1200.0),
                                             (1200.0, 1500.0), (1500.0, 1800.0)]
    mb = [m / 1024 for _, _, m in trend]
    assert abs(mb[0] - 1002.4) < 0.1 and abs(mb[1] - 1007.4) < 0.1      # medians of 0..290 s and 300..590 s
    assert all(abs(x - 1010.0) < 1e-3 for x in mb[2:])                 # plateau


def test_rss_trend_short_runs_and_no_samples():
    assert rss_trend([], 300.0) == []
    assert len(rss_trend([(0.0, 1), (50.0, 2)], 90.0)) == 1             # never a window under a minute
    five = rss_trend([(float(t), t) for t in range(300)], 300.0)
    assert len(five) == 5 and five[-1][2] == 269                        # the last window takes the end sample too


def test_rss_halves_after_the_warmup():
    from dpv_sensor.tools.soak import rss_halves
    # 12 min, a sample every 5 s: 1000 kB for the first 7 min, then 1100 kB
    samples = [(float(t), 1000 if t < 420 else 1100) for t in range(0, 720, 5)]
    h = rss_halves(samples, 720.0)
    assert h == {'windows_s': [120.0, 420.0, 720.0], 'earlier_kib': 1000, 'later_kib': 1100, 'ratio': 1.1}
    assert rss_halves(samples, 100.0)['ratio'] is None and rss_halves([], 720.0)['windows_s'] is None


def test_resets_are_split_by_cause_and_loop_boundary():
    from dpv_sensor.tools.soak import classify_resets
    loop_starts_ns = [1_000_000_100 * 10**9, 1_000_000_110 * 10**9]
    prefix = '[INFO] [{}] [dpv_sensor]: [dpv_sensor.stream.estimator] estimator reset: '
    log = '\n'.join([
        prefix.format('1000000050.250000000') + 'odometry jumped',             # before the first loop start
        prefix.format('1000000101.500000000') + 'time gap 0.533 s in the camera stream > reset_time_gap 0.5 s',
        prefix.format('1000000106.000000000') + 'odometry jumped',             # the loop's jump, 6 s late: busy
        prefix.format('1000000108.000000000') + 'odometry jumped',             # a second one in the same loop
        prefix.format('1000000110.500000000') + 'odometry jumped',             # the next loop's
        '[INFO] [1000000111.000000000] [dpv_sensor]: ready: nothing to count here'])
    assert classify_resets(log, loop_starts_ns) == {
        'odometry jumped': 2, 'time gap # s in the camera stream > reset_time_gap # s': 1, 'loop_boundary': 2}


def test_accounting_of_every_image_sent():
    from dpv_sensor.tools.soak import accounting
    diag = {'frames_received': '90', 'lost.transport': '10', 'lost.rmw': '7', 'lost.stamp_gaps_only': '3',
            'frames_processed': '60', 'dropped_total': '29'}
    acc = accounting(diag, 101)
    assert acc['unaccounted'] == 2 and acc['received_not_done'] == 1 and acc['lost_rmw'] == 7
