"""StreamLoss: images missing from the stamps and reported lost by the middleware, each counted once."""
import pytest

from dpv_sensor.ros.stream_loss import Gap, StreamLoss

MS = 1_000_000
P = 33 * MS          # a 33 ms camera


def feed(loss, frame_indices, base=10**18):
    """Images at base + i * P for each index i; returns the gaps."""
    return [loss.on_image(base + i * P) for i in frame_indices]


def test_gaps_before_the_period_is_known_count_once_it_is_then_missing_images_are_counted():
    loss = StreamLoss(min_intervals=3)
    # frames 0, 2: one interval of 2 periods, but no period is known yet -> not counted yet
    assert feed(loss, [0, 2]) == [None, None]
    assert loss.period_ns is None and loss.lost_total == 0
    feed(loss, [3, 4])                       # intervals 2P, P, P: low quantile = P, ratios P, P, P
    assert loss.period_ns == P
    assert loss.lost_total == 1 and loss.gaps == 1     # the stream runs at P: frame 1 was lost
    gap = loss.on_image(10**18 + 8 * P)      # 4 -> 8: frames 5, 6, 7 missing
    assert gap.missing == 3 and gap.interval_ns == 4 * P and gap.period_ns == P
    assert not gap.explained and gap.camera_gap_ns == 4 * P
    assert gap.state == 'pending' and loss.lost_total == 1    # no evidence yet: the camera may have slowed down
    feed(loss, [9])                          # one period later: the camera runs at its rate, the 3 were lost
    assert gap.state == 'confirmed'
    assert loss.counts()['lost.transport'] == 4 and loss.lost_stamp_gap_only == 4 and loss.lost_rmw == 0
    assert loss.gaps == 2 and loss.unexplained_gaps == 2


def test_period_from_a_low_quantile_survives_heavy_loss():
    """Most intervals span several periods (only every 3rd or 4th image arrives); the median of the raw intervals
    would be 3P, the estimate stays P."""
    loss = StreamLoss(min_intervals=4, quantile=0.1)
    feed(loss, [0, 1, 4, 7, 11, 14, 18, 19, 21, 22])   # intervals P, 3P, 3P, 4P, 3P, 4P, P, 2P, P
    assert loss.period_ns == P
    # the first 4 intervals are judged once the period is known (1->4, 4->7, 7->11: 2 + 2 + 3), the later ones each
    # confirmed by a later interval of one period: 11->14, 14->18 (2 + 3), 19->21 (1)
    assert loss.lost_stamp_gap_only == 13 and loss.rate_changes == 0


def test_jitter_is_not_a_gap_and_1_4_periods_is_not_a_lost_image():
    loss = StreamLoss(min_intervals=4)
    t = 0
    for dt in (P, P + 2 * MS, P - 2 * MS, P, P + 1 * MS):
        t += dt
        loss.on_image(t)
    assert abs(loss.period_ns - P) <= 1 * MS
    assert loss.on_image(t + int(1.4 * P)) is None
    assert loss.lost_total == 0 and loss.gaps == 0


def test_report_before_the_gap_explains_it_and_is_not_counted_twice():
    loss = StreamLoss(min_intervals=3)
    feed(loss, [0, 1, 2, 3])
    loss.on_rmw_lost(2)                      # the event is handled first ...
    gap = loss.on_image(10**18 + 6 * P)      # ... then the image after the hole: frames 4, 5 missing
    assert gap.missing == 2 and gap.matched == 2 and gap.explained and gap.camera_gap_ns == P
    assert (loss.lost_rmw, loss.lost_stamp_gap_only, loss.lost_total) == (2, 0, 2)
    assert loss.unexplained_gaps == 0 and loss.gaps == 1


def test_report_after_the_gap_explains_it_later():
    loss = StreamLoss(min_intervals=3)
    feed(loss, [0, 1, 2, 3])
    gap = loss.on_image(10**18 + 7 * P)      # frames 4, 5, 6 missing; no report yet
    feed(loss, [8])
    assert not gap.explained and loss.lost_total == 3 and loss.unexplained_gaps == 1
    loss.on_rmw_lost(1)
    assert gap.matched == 1 and not gap.explained and loss.lost_total == 3
    loss.on_rmw_lost(2)                      # now all three are reported: the same gap, no new images lost
    assert gap.explained and gap.camera_gap_ns == P
    assert (loss.lost_rmw, loss.lost_stamp_gap_only, loss.lost_total) == (3, 0, 3)
    assert loss.unexplained_gaps == 0


def test_reports_without_a_gap_and_gaps_without_reports_both_count():
    loss = StreamLoss(min_intervals=3)
    feed(loss, [0, 1, 2, 3])
    loss.on_rmw_lost(4)                      # 4 reported ...
    gap = loss.on_image(10**18 + 5 * P)      # ... one missing in the stamps: matched with one report
    assert gap.explained and loss.lost_total == 4
    feed(loss, [8])                          # a later gap of 2 (frames 6, 7) takes two of the 3 spare reports
    assert loss.lost_total == 4 and loss.lost_stamp_gap_only == 0
    feed(loss, [11, 12])                     # 9, 10 missing: one spare report left, one image unreported
    assert (loss.lost_rmw, loss.lost_stamp_gap_only, loss.lost_total) == (4, 1, 5)
    assert loss.unexplained_gaps == 1


def test_time_going_backwards_restarts_the_estimate():
    loss = StreamLoss(min_intervals=3)
    feed(loss, [0, 1, 2, 3])
    assert loss.on_image(10**18 - 100 * P) is None
    assert loss.period_ns is None
    assert loss.on_image(10**18 - 95 * P) is None      # 5P after the restart: no period yet, not counted
    assert loss.on_image(10**18 - 95 * P) is None      # a repeated stamp: nothing
    assert loss.lost_total == 0


def test_counts_and_arguments():
    loss = StreamLoss()
    assert loss.counts() == {'lost.transport': 0, 'lost.rmw': 0, 'lost.stamp_gaps_only': 0,
                             'lost.sequence_gaps_only': 0, 'lost.gaps': 0, 'lost.unexplained_gaps': 0,
                             'input_rate_changes': 0, 'input_stamp_jumps': 0, 'input_sequence_restarts': 0,
                             'input_period_ms': 'n/a'}
    loss.on_rmw_lost(0)
    loss.on_rmw_lost(-3)
    assert loss.lost_rmw == 0
    with pytest.raises(ValueError):
        StreamLoss(history=0)
    assert Gap(10, 2, 4, 4).camera_gap_ns == 2 and Gap(10, 2, 4, 3).camera_gap_ns == 10



def stream(loss, t0, period_ns, n):
    """n images `period_ns` apart after t0; returns the last stamp."""
    t = t0
    for _ in range(n):
        t += period_ns
        loss.on_image(t)
    return t


@pytest.mark.parametrize('new_hz', [15.0, 4.0, 2.0])
def test_a_camera_that_lowers_its_rate_loses_nothing(new_hz):
    """Auto-exposure: 30 Hz, then a lower rate with every image arriving: no image counted lost, the period is
    re-estimated, and a loss at the new rate is still counted."""
    loss = StreamLoss()
    t = stream(loss, 0, P, 40)
    new = int(NS / new_hz)
    t = stream(loss, t, new, 60)
    assert loss.lost_total == 0 and loss.rate_changes == 1 and loss.stamp_jumps == 0, loss.counts()
    assert abs(loss.period_ns - new) < MS
    t += 2 * new                              # one image lost at the new rate, then the stream goes on
    loss.on_image(t)
    stream(loss, t, new, 3)
    assert loss.lost_total == 1, loss.counts()


def test_a_stamp_jump_is_a_discontinuity_not_lost_images():
    loss = StreamLoss()
    t = stream(loss, 0, P, 40)
    assert loss.on_image(t + 3600 * NS) is None           # all streams 1 h ahead (or a /clock jump)
    stream(loss, t + 3600 * NS, P, 40)
    assert loss.lost_total == 0 and loss.stamp_jumps == 1 and loss.last_jump_ns == 3600 * NS, loss.counts()
    assert loss.period_ns == P


def test_a_burst_then_a_slow_stream_counts_no_phantom_losses():
    """200 images at 1 ms spacing, then a clean 4 Hz stream: nothing lost in either."""
    loss = StreamLoss()
    t = stream(loss, 0, MS, 200)
    stream(loss, t, NS // 4, 40)
    assert loss.lost_total == 0 and loss.rate_changes == 1, loss.counts()


def test_reported_losses_during_a_rate_drop_still_count():
    loss = StreamLoss()
    t = stream(loss, 0, P, 40)
    loss.on_rmw_lost(1)
    t += 2 * P
    gap = loss.on_image(t)                   # the report explains this gap: counted at once
    assert gap.explained and loss.lost_total == 1
    stream(loss, t, 2 * P, 20)               # then 15 Hz: no more
    assert loss.lost_total == 1 and loss.rate_changes == 1, loss.counts()


NS = 1_000_000_000


def test_images_lost_before_the_period_is_known_are_counted_once_it_is():
    from dpv_sensor.ros.stream_loss import StreamLoss
    sl = StreamLoss(min_intervals=8)
    period = 33_333_333
    # images 1-3 lost right at the start, then a clean stream: 3 lost, counted once the period is known
    stamps = [0] + [k * period for k in range(4, 20)]
    for t in stamps:
        sl.on_image(t)
    assert sl.lost_total == 3 and sl.gaps == 1
    # a loss report for them afterwards matches the gap instead of counting the images twice
    sl.on_rmw_lost(3)
    assert sl.lost_total == 3 and sl.lost_rmw == 3 and sl.lost_stamp_gap_only == 0


@pytest.mark.parametrize('period_ns, gap_periods, jump, lost', [
    (200 * MS, 7.9, False, 7),     # 5 Hz: 8 periods (1.6 s) is the line, above max_loss_gap (1 s)
    (200 * MS, 8.1, True, 0),
    (33 * MS, 0.9 * NS / (33 * MS), False, 26),    # 30 Hz: max_loss_gap (1 s) is the line, above 8 periods
    (33 * MS, 1.1 * NS / (33 * MS), True, 0),
])
def test_the_stamp_jump_rule_either_side_of_its_threshold(period_ns, gap_periods, jump, lost):
    """A stamp interval longer than max(max_loss_gap, 8 periods) is a discontinuity (nothing counted lost); one just
    shorter is images lost in transport (round(interval / period) - 1 of them, once the stream after it runs at
    the rate again)."""
    loss = StreamLoss()
    t = stream(loss, 0, period_ns, 40)
    t += int(round(gap_periods * period_ns))
    loss.on_image(t)
    stream(loss, t, period_ns, 20)
    assert loss.stamp_jumps == int(jump), loss.counts()
    assert loss.lost_total == lost, loss.counts()
