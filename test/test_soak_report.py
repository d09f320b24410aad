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
