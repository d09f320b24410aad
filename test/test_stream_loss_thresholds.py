"""StreamLoss (dpv_sensor.ros.stream_loss): every rule of the module just either side of its threshold, against
counts worked out by hand (never from the constants under test).

The stream: a 33 ms camera, 40 images one period apart (the period is known), then the intervals of the case, then
20 images one period apart (the camera still runs at its rate: pending gaps are confirmed). The documented rules:

- gap: an interval of 1.5 periods and more is ``round(interval / period) - 1`` lost images (1.4: jitter, none);
- stamp jump: an interval over max(max_loss_gap_ns = 1 s, 8 periods) is a discontinuity (nothing lost), unless
  the middleware already reported at least the ``round(interval / period) - 1`` images it would hold;
- rate change: 3 consecutive unreported gaps within 15 % of their median are a slower camera (withdrawn);
- at most 8 gaps wait for confirmation: a 9th confirms the oldest;
- with sequence numbers: a step of k is k - 1 lost images; a jump is judged on the interval less the missing images'
  periods; 3 equal intervals of 1.5 periods and more without a sequence gap are a rate change.
"""
import pytest

from dpv_sensor.ros.stream_loss import StreamLoss

MS = 1_000_000
NS = 1_000_000_000
P = 33 * MS          # a 33 ms camera: 8 periods are 264 ms, so at this rate max_loss_gap (1 s) is the jump line


def run(loss, intervals_ns, before=40, after=20, seq=False, reports_before_last=0):
    """`before` images one period apart, then one image after each interval of `intervals_ns`, then `after` images
    one period apart; with `seq`, consecutive publication sequence numbers (a step of k for an interval given as
    (ns, k)); `reports_before_last`: losses the middleware reports just before the last of `intervals_ns` ends.
    Returns the Gap (or None) each of `intervals_ns` ended."""
    t, n = 0, 1
    loss.on_image(t, n if seq else None)
    for _ in range(before):
        t, n = t + P, n + 1
        loss.on_image(t, n if seq else None)
    ended = []
    for i, item in enumerate(intervals_ns):
        interval, step = item if isinstance(item, tuple) else (item, 1)
        if i == len(intervals_ns) - 1 and reports_before_last:
            loss.on_rmw_lost(reports_before_last)
        t, n = t + interval, n + step
        ended.append(loss.on_image(t, n if seq else None))
    for _ in range(after):
        t, n = t + P, n + 1
        loss.on_image(t, n if seq else None)
    return ended


@pytest.mark.parametrize('interval_ns, lost', [
    (P + 2 * MS, 0),                 # jitter
    (46_200_000, 0),                 # 1.4 periods: jitter, not a lost image
    (49_170_000, 0),                 # 1.49 periods: just under the line
    (49_500_000, 1),                 # 1.5 periods exactly: on the line, one image lost (round(1.5) = 2)
    (56_100_000, 1),                 # 1.7 periods: one image lost
    (66_000_000, 1),                 # 2 periods
    (79_200_000, 1),                 # 2.4 periods: rounds to 2
    (85_800_000, 2),                 # 2.6 periods: rounds to 3, two lost
    (99_000_000, 2),                 # 3 periods
])
def test_the_gap_rule_either_side_of_one_and_a_half_periods(interval_ns, lost):
    """One interval of the stream: 1.5 periods and more is round(interval / period) - 1 lost images."""
    loss = StreamLoss()
    (gap,) = run(loss, [interval_ns])
    assert loss.period_ns == P
    assert loss.lost_total == lost and loss.lost_stamp_gap_only == lost, (interval_ns, loss.counts())
    assert loss.gaps == (1 if lost else 0) and loss.stamp_jumps == 0 and loss.rate_changes == 0
    if lost:
        assert gap.missing == lost and gap.state == 'confirmed' and gap.camera_gap_ns == interval_ns
    else:
        assert gap is None


@pytest.mark.parametrize('interval_ns, lost', [
    (46_200_000, 0),                 # 1.4 periods
    (56_100_000, 1),                 # 1.7 periods
    (99_000_000, 2),                 # 3 periods
])
def test_the_gap_rule_for_intervals_seen_before_the_period_was_known(interval_ns, lost):
    """The same line for the first intervals of a stream, judged once the period is known."""
    loss = StreamLoss(min_intervals=8)
    t = 0
    loss.on_image(t)
    t += interval_ns                 # the first interval: no period yet
    loss.on_image(t)
    for _ in range(12):
        t += P
        loss.on_image(t)
    assert loss.period_ns == P and loss.lost_total == lost, loss.counts()


@pytest.mark.parametrize('periods, reports, jump, gaps, lost_rmw, lost_total', [
    # 40 periods (1.32 s, over 1 s and over 8 periods) hold 39 images
    (40, 0, True, 0, 0, 0),          # nothing reported: a discontinuity
    (40, 38, True, 0, 38, 38),       # one image short of what the gap holds: still a discontinuity (reports count)
    (40, 39, False, 1, 39, 39),      # every image of the gap reported one by one: transport loss, not a jump
    (40, 40, False, 1, 40, 40),      # one report more than the gap holds: a loss, the spare report counts too
    (60, 58, True, 0, 58, 58),       # 2 s: 59 images, 58 reported
    (60, 59, False, 1, 59, 59),      # 2 s, all 59 reported
])
def test_a_long_gap_the_middleware_reported_image_by_image_is_not_a_stamp_jump(periods, reports, jump, gaps,
                                                                                lost_rmw, lost_total):
    """The stamp-jump rule of an unsequenced stream: an interval over max(1 s, 8 periods) is a jump unless the
    losses reported before it account for every image it holds (round(interval / period) - 1)."""
    loss = StreamLoss()
    (gap,) = run(loss, [periods * P], reports_before_last=reports)
    assert loss.stamp_jumps == int(jump), loss.counts()
    assert (loss.gaps, loss.lost_rmw, loss.lost_total) == (gaps, lost_rmw, lost_total), loss.counts()
    assert loss.lost_stamp_gap_only == 0 and loss.unexplained_gaps == 0
    if jump:
        assert gap is None and loss.last_jump_ns == periods * P
    else:
        assert gap.missing == periods - 1 and gap.explained and gap.camera_gap_ns == P


@pytest.mark.parametrize('period_ns, interval_ns, jump, lost', [
    (33 * MS, NS, False, 29),                  # 1 s exactly at 30 Hz: on the line (30.3 periods: 29 lost)
    (33 * MS, NS + 1, True, 0),                # 1 ns over it: a jump
    (200 * MS, 1_600_000_000, False, 7),       # 5 Hz: 8 periods exactly (1.6 s, over 1 s): 7 lost
    (200 * MS, 1_600_000_001, True, 0),        # 1 ns over 8 periods
])
def test_the_stamp_jump_line_itself_is_not_a_jump(period_ns, interval_ns, jump, lost):
    loss = StreamLoss()
    t = 0
    for _ in range(41):
        loss.on_image(t)
        t += period_ns
    t += interval_ns - period_ns
    loss.on_image(t)
    for _ in range(20):
        t += period_ns
        loss.on_image(t)
    assert loss.stamp_jumps == int(jump) and loss.lost_total == lost, loss.counts()


@pytest.mark.parametrize('intervals_ns, rate_changes, lost', [
    ((66 * MS, 66 * MS, 66 * MS), 1, 0),             # 3 equal gaps: a slower camera, nothing lost
    ((99 * MS, 99 * MS, 99 * MS), 1, 0),             # likewise at a third of the rate
    ((66 * MS, 74_250_000, 66 * MS), 1, 0),          # 2.25 periods: 12.5 % off the median 2 periods, within 15 %
    ((66 * MS, 79_200_000, 66 * MS), 0, 3),          # 2.4 periods: 20 % off: three gaps of one lost image each
    ((66 * MS, 66 * MS), 0, 2),                      # only 2 equal gaps, then the old rate: two images lost
])
def test_a_run_of_equal_gaps_is_a_rate_change_either_side_of_fifteen_percent(intervals_ns, rate_changes, lost):
    loss = StreamLoss()
    run(loss, list(intervals_ns))
    assert (loss.rate_changes, loss.lost_total) == (rate_changes, lost), loss.counts()


def test_the_ninth_pending_gap_confirms_the_oldest():
    """Gaps of 2 and 3 periods in turn (never 3 within 15 %) with no interval of one period between them: 8 wait
    for the stream to confirm them; the 9th confirms the oldest (a 2-period gap: one image)."""
    loss = StreamLoss()
    run(loss, [66 * MS, 99 * MS] * 4, after=0)
    assert loss.lost_total == 0 and loss.gaps == 0, loss.counts()
    loss2 = StreamLoss()
    run(loss2, [66 * MS, 99 * MS] * 4 + [66 * MS], after=0)
    assert loss2.lost_total == 1 and loss2.gaps == 1, loss2.counts()


@pytest.mark.parametrize('interval_ns, step, jump, lost_seq', [
    (40 * P, 40, False, 39),         # 39 missing by the numbers: 40 periods less 39 is one period
    (40 * P, 1, True, 0),            # no sequence gap: 1.32 s is a stamp jump
    (NS, 1, False, 0),               # 1 s exactly with no sequence gap: on the line, a slow interval, not a jump
    (NS + 1, 1, True, 0),            # 1 ns over: a jump
    (NS + 3 * P, 4, False, 3),       # 3 missing: judged on the interval less their 3 periods, 1 s: on the line
    (NS + 3 * P + 1, 4, True, 3),    # 1 ns over it: a jump, and the 3 the numbers say were lost still count
])
def test_a_sequenced_stream_judges_jumps_beyond_the_missing_images(interval_ns, step, jump, lost_seq):
    loss = StreamLoss()
    run(loss, [(interval_ns, step)], seq=True)
    assert loss.stamp_jumps == int(jump), loss.counts()
    assert loss.lost_sequence_gap_only == lost_seq and loss.lost_stamp_gap_only == 0, loss.counts()


@pytest.mark.parametrize('interval_ns, rate_changes', [
    (46_200_000, 0),                 # 1.4 periods, three times: jitter
    (49_500_000, 1),                 # 1.5 periods exactly, three times: a slower camera
    (66 * MS, 1),                    # 2 periods
])
def test_a_sequenced_stream_slowing_down_is_a_rate_change_from_one_and_a_half_periods(interval_ns, rate_changes):
    loss = StreamLoss()
    run(loss, [interval_ns] * 3, seq=True, after=0)
    assert loss.rate_changes == rate_changes and loss.lost_total == 0, loss.counts()


@pytest.mark.parametrize('first_ns, lost', [
    (40 * P, 0),                     # 1.32 s: over max(1 s, 8 periods), a jump: nothing lost
    (NS, 29),                        # 1 s exactly: on the line, not a jump: round(1000 / 33) - 1 = 29 lost
])
def test_a_stamp_jump_before_the_period_is_known_loses_nothing(first_ns, lost):
    """The stream's first interval, judged when the period becomes known (12 one-period intervals later): the jump
    rule holds there too."""
    loss = StreamLoss(min_intervals=8)
    t = 0
    loss.on_image(t)
    t += first_ns
    loss.on_image(t)
    for _ in range(12):
        t += P
        loss.on_image(t)
    assert loss.period_ns == P
    assert loss.lost_total == lost and loss.lost_stamp_gap_only == lost, loss.counts()


@pytest.mark.parametrize('intervals_ns, rate_changes', [
    ([66 * MS, 74 * MS, 66 * MS], 1),            # 74 ms is 12 % off the run's median, 66 ms: a slower camera
    ([66 * MS, 79_200_000, 66 * MS], 0),         # 79.2 ms is 20 % off: not one rate
])
def test_a_sequenced_stream_slowing_down_needs_its_intervals_within_fifteen_percent(intervals_ns, rate_changes):
    loss = StreamLoss()
    run(loss, intervals_ns, seq=True)
    assert loss.rate_changes == rate_changes and loss.lost_total == 0, loss.counts()


def test_sequence_gaps_keep_the_period_of_the_images_that_came():
    """Every other image lost for 70 intervals (66 ms, a sequence step of 2): the camera still runs at 33 ms; each
    interval stands for two periods, so the period stays 33 ms and each step is one lost image."""
    loss = StreamLoss()
    run(loss, [(2 * P, 2)] * 70, seq=True, after=0)
    assert loss.period_ns == P and loss.rate_changes == 0, loss.counts()
    assert loss.lost_total == 70 and loss.lost_sequence_gap_only == 70, loss.counts()


def test_a_gap_still_pending_when_the_camera_jumps_is_counted():
    """A 2-period gap (one image lost, pending: it might start a slower rate), then a 2 s stamp jump: the jump
    restarts the stream, and the pending gap counts as the loss it was."""
    loss = StreamLoss()
    run(loss, [2 * P, 2 * NS], after=0)
    assert loss.stamp_jumps == 1 and loss.lost_total == 1 and loss.lost_stamp_gap_only == 1, loss.counts()


def test_a_sequence_gaps_camera_gap_is_its_interval_less_the_missing_images():
    """5 periods with a sequence step of 3: 2 images lost, and the camera itself paused 5 - 2 = 3 periods (99 ms)."""
    loss = StreamLoss()
    (gap,) = run(loss, [(5 * P, 3)], seq=True, after=0)
    assert gap.missing == 2 and gap.by_sequence and gap.camera_gap_ns == 3 * P


def test_a_partly_reported_gap_is_not_withdrawn_by_a_rate_change():
    """The camera slows to every third frame (3-period intervals) just as the middleware reports one loss: the first
    3-period gap (2 images) has one matched, so it is not the new rate's: confirmed, 2 lost; the unreported ones
    that follow are the slower camera (withdrawn)."""
    loss = StreamLoss()
    run(loss, [3 * P] * 24, after=0)
    assert loss.lost_total == 0 and loss.rate_changes == 1, loss.counts()      # the case without the report
    loss = StreamLoss()
    t = 0
    for _ in range(41):
        loss.on_image(t)
        t += P
    t -= P
    loss.on_rmw_lost(1)
    for _ in range(24):
        t += 3 * P
        loss.on_image(t)
    assert loss.rate_changes == 1 and loss.lost_total == 2 and loss.lost_rmw == 1, loss.counts()


def test_a_sequenced_rate_change_keeps_a_period_and_a_later_jump_is_seen():
    """A sequenced 33 ms stream slows to 66 ms (three intervals without a sequence gap: a rate change); its period
    is then 66 ms at once, and a 5 s interval after it is a stamp jump."""
    loss = StreamLoss()
    run(loss, [66 * MS] * 3 + [5 * NS], seq=True, after=0)
    assert loss.rate_changes == 1 and loss.stamp_jumps == 1, loss.counts()
