"""Images lost before the callback counted from the publisher's sequence numbers (PublicationSequence, StreamLoss),
with the stamp rules where the numbers say nothing and the middleware's reports matched, each image counted once.
Every expected figure is worked out by hand in the comments."""
from dpv_sensor.ros.sequence_numbers import PublicationSequence
from dpv_sensor.ros.stream_loss import StreamLoss

MS = 1_000_000
P = 33 * MS                # a 33 ms camera
BASE = 10**18


def test_sequence_steps_count_the_missing_samples_per_source():
    seq = PublicationSequence(trust_after=2)
    assert seq.step('cam', 1) is None            # first sample: nothing to compare with
    assert seq.step('cam', 2) == 0
    assert seq.step('cam', 5) == 2               # 3 and 4 never arrived
    assert seq.step('other', 40) is None         # another source has its own numbers
    assert seq.step('cam', 6) == 0 and seq.step('other', 42) == 1


def test_unknown_numbers_and_a_restarted_publisher_say_nothing_until_a_run_of_forward_steps():
    seq = PublicationSequence(trust_after=2)
    for unknown in (None, 0, 2**64 - 1):         # no number, 0, the middleware's 'unsupported'
        assert seq.step('cam', unknown) is None
    assert seq.unavailable == 3
    assert [seq.step('cam', n) for n in (10, 11)] == [None, 0]
    assert seq.step('cam', 1) is None and seq.restarts == 1 and seq.last_restart == ('cam', 11, 1)
    assert seq.step('cam', 3) is None            # 1 -> 3: within trust_after steps of the restart
    assert seq.step('cam', 4) is None
    assert seq.step('cam', 7) == 2               # trusted again: 5 and 6 lost
    assert seq.step('cam', 7) is None and seq.restarts == 2     # a repeated number is no forward step either


def run(loss, frames, seqs=None, source='cam'):
    """Images at BASE + i * P for each frame index i, numbered `seqs` (default: i + 1); returns the gaps."""
    seqs = seqs if seqs is not None else [i + 1 for i in frames]
    return [loss.on_image(BASE + i * P, seq=s, source=source) for i, s in zip(frames, seqs)]


def test_a_burst_whose_missing_images_fill_the_stamp_hole_is_transport_loss_not_a_stamp_jump():
    loss = StreamLoss()
    run(loss, range(10))                          # frames 0..9, numbers 1..10
    gap = loss.on_image(BASE + 105 * P, seq=106, source='cam')   # frames 10..104 (numbers 11..105) never arrived
    # 95 missing; the stamp interval, 96 periods (3.17 s, over max_loss_gap), is exactly what they explain
    assert gap.missing == 95 and gap.by_sequence and gap.explained and gap.camera_gap_ns == P
    assert loss.stamp_jumps == 0 and loss.lost_total == 95 and loss.lost_sequence_gap_only == 95
    run(loss, [106, 107], seqs=[107, 108])        # then at the rate again: nothing more
    counts = loss.counts()
    assert counts['lost.transport'] == 95 and counts['lost.sequence_gaps_only'] == 95 and counts['lost.gaps'] == 1
    assert counts['lost.stamp_gaps_only'] == 0 and counts['lost.unexplained_gaps'] == 0


def test_a_stamp_gap_without_a_sequence_gap_loses_nothing_and_equal_ones_are_a_rate_change():
    loss = StreamLoss()
    run(loss, range(10), seqs=range(1, 11))
    # stamps 3 periods apart, numbers consecutive: the camera slowed down (the stamp rule alone would wait, then
    # withdraw); three equal intervals are a new rate
    for k, frame in enumerate((12, 15, 18)):
        assert loss.on_image(BASE + frame * P, seq=11 + k, source='cam') is None
    assert loss.lost_total == 0 and loss.rate_changes == 1 and loss.period_ns == 3 * P


def test_a_stamp_jump_beyond_what_the_missing_images_explain_is_still_a_discontinuity():
    loss = StreamLoss()
    run(loss, range(10))
    # one image lost (number 11) but the stamps moved an hour: 1 lost, 1 stamp jump
    gap = loss.on_image(BASE + 9 * P + 3600 * 1000 * MS, seq=12, source='cam')
    assert loss.stamp_jumps == 1 and loss.lost_total == 1 and gap.missing == 1
    assert gap.camera_gap_ns == 3600 * 1000 * MS - P      # the camera stream itself stalled: the restart fires


def test_reports_before_and_after_a_sequence_gap_are_matched_not_counted_twice():
    loss = StreamLoss()
    run(loss, range(10))
    loss.on_rmw_lost(2)                            # the middleware reports 2 losses first ...
    gap = loss.on_image(BASE + 13 * P, seq=14, source='cam')    # ... then numbers 11, 12, 13 are missing
    assert gap.missing == 3 and gap.matched == 2
    assert loss.lost_rmw == 2 and loss.lost_sequence_gap_only == 1 and loss.lost_total == 3
    loss.on_rmw_lost(1)                            # the third report comes late: it is the same image
    assert loss.lost_rmw == 3 and loss.lost_sequence_gap_only == 0 and loss.lost_total == 3
    loss.on_rmw_lost(1)                            # a report no gap shows (yet): counted as reported
    assert loss.lost_total == 4


def test_a_restarted_publisher_falls_back_to_the_stamp_rules():
    loss = StreamLoss()
    loss.sequence = PublicationSequence(trust_after=2)
    run(loss, range(10))                           # numbers 1..10
    # the driver restarts: numbers from 1 again; its first image comes 3 periods later (2 images lost, which the
    # numbers cannot show), then one period: the stamp rule counts the 2
    gap = loss.on_image(BASE + 12 * P, seq=1, source='cam')
    assert gap is not None and not gap.by_sequence and gap.state == 'pending' and loss.lost_total == 0
    loss.on_image(BASE + 13 * P, seq=2, source='cam')
    assert gap.state == 'confirmed' and loss.lost_total == 2 and loss.lost_stamp_gap_only == 2
    loss.on_image(BASE + 14 * P, seq=3, source='cam')     # the second forward step: trusted again from the next
    gap = loss.on_image(BASE + 16 * P, seq=5, source='cam')
    assert gap.by_sequence and gap.missing == 1 and loss.lost_total == 3
    assert loss.counts()['input_sequence_restarts'] == 1


def test_without_numbers_the_stamp_rules_count_as_before():
    loss = StreamLoss()
    run(loss, range(10), seqs=[0] * 10)
    gap = loss.on_image(BASE + 12 * P, seq=0, source='cam')
    assert gap.missing == 2 and gap.state == 'pending'
    loss.on_image(BASE + 13 * P, seq=0, source='cam')
    assert loss.lost_total == 2 and loss.lost_stamp_gap_only == 2 and loss.lost_sequence_gap_only == 0
