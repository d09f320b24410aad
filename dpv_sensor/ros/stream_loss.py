"""Images lost between the camera and the node: counted only where there is evidence of a loss, each lost image
once. Pure Python (no rclpy).

Evidence of a loss is

- the publisher's sequence numbers where the middleware passes them (``sequence_numbers``: a step from n to n + k
  means k - 1 samples of that publisher were lost before the callback, whatever dropped them and whatever their
  stamps say): the first evidence, and while they are known the stamp gaps below are not judged (a stamp gap with
  no sequence gap is a slower camera or a stall, never a loss), or
- the middleware's report (rclpy's message-lost event, where the middleware gives it: Fast DDS does for best-effort
  readers, from the writer's sequence numbers), which says *how many* samples were lost, or
- a gap in the header stamps against the camera's frame period, confirmed by the stream around it: an interval of
  `n` periods (n >= 2, rounded; 1.5 periods and more) means `n - 1` images are missing once a later interval of one
  period shows the camera still runs at that rate. This is the rule where the numbers say nothing (no numbers,
  the first sample, a publisher that restarted: its numbers went back).

The frame period is estimated from the stamps of the images that arrive: a low quantile of the recent intervals
picks an interval of one period even when many images are lost (a median would pick two or more), and the period is
the median of every recent interval divided by its whole number of periods. It is re-estimated when the rate
changes: `rate_change_intervals` consecutive gaps of the same length (within 15 %) without a loss report are a
camera that lowered its rate (auto-exposure, a driver setting, a burst followed by the normal rate), not lost images:
those gaps are withdrawn and the period becomes their length. A stamp interval longer than `max_loss_gap_ns` (and 8
periods) that no report explains is a discontinuity (the camera stalled, or its clock or /clock jumped): counted in
`stamp_jumps`, never as lost images, and the estimate restarts after it.

Each missing image in a stamp gap is matched with a reported loss when one is unmatched (in either order: the event
may be handled before or after the image that ends the gap), so

    lost_total = lost_rmw + lost_stamp_gap_only + lost_sequence_gap_only

where ``lost_stamp_gap_only`` and ``lost_sequence_gap_only`` are missing images no report accounts for (a reliable
reader, a middleware that does not report, a reliable writer whose history overflowed) and ``lost_rmw`` includes
reports no gap shows (irregular stamps, or the stream ended). A sequence gap is transport loss by its nature (the
camera ran: its stamp interval is explained by the missing images); a stamp jump beyond what the missing images
explain is still a discontinuity.

A gap counts as *transport loss* (:attr:`Gap.explained`) when the sequence numbers show it, or once every image
missing in it is matched with a reported loss: the camera kept running, so the camera stream's own gap is one period
(:attr:`Gap.camera_gap_ns`), and a consumer that restarts on stream interruptions should not restart for it. Other
gaps keep their stamp interval.
"""
from __future__ import annotations

import collections
import statistics
from dataclasses import dataclass

from dpv_sensor.ros.sequence_numbers import PublicationSequence

PENDING, CONFIRMED, WITHDRAWN = 'pending', 'confirmed', 'withdrawn'


@dataclass
class Gap:
    """One interval in the stamps with images missing in it (updated when late loss reports match it)."""
    interval_ns: int     # the stamp interval between the two images received
    period_ns: int       # the estimated frame period at the time
    missing: int         # images missing in it (>= 1)
    matched: int = 0     # of them, matched with losses the RMW reported
    state: str = CONFIRMED   # pending (waiting for the next interval), confirmed, or withdrawn (a rate change)
    by_sequence: bool = False   # counted from the publisher's sequence numbers (transport loss by its nature)

    @property
    def reported(self) -> bool:
        """Every missing image is matched with a loss the middleware reported."""
        return self.matched >= self.missing

    @property
    def explained(self) -> bool:
        """Every missing image is a transport loss (sequence numbers, or reports): the camera did not stall."""
        return self.by_sequence or self.reported

    @property
    def settled(self) -> bool:
        """Nothing later can change how this interval counts: explained by reports, or withdrawn (a rate change)."""
        return self.explained or self.state == WITHDRAWN

    @property
    def camera_gap_ns(self) -> int:
        """The gap of the camera stream itself: one period when the loss is explained, else the stamp interval (a
        sequence gap: the stamp interval less the missing images' periods, at least one period)."""
        if self.by_sequence:
            return max(self.period_ns, self.interval_ns - self.missing * self.period_ns)
        return self.period_ns if self.explained else self.interval_ns


JUMP_PERIODS = 8      # a stamp interval over this many frame periods (and over max_loss_gap) is a jump


class StreamLoss:
    """Counts images lost in a camera stream (see the module docs). Not thread-safe: call from one thread.

    history: how many recent intervals the period estimate uses; quantile: the low quantile that picks a
    one-period interval; min_intervals: intervals needed before the period is known (the gaps among them are
    judged once it is);
    keep_gaps: how many recent unexplained gaps late loss reports may still match; rate_change_intervals:
    consecutive equal gaps that make a new rate; max_pending: gaps waiting for confirmation before the oldest is
    confirmed anyway; max_loss_gap_ns: the longest unreported stamp gap counted as lost images."""

    def __init__(self, history: int = 64, quantile: float = 0.1, min_intervals: int = 8, keep_gaps: int = 16,
                 rate_change_intervals: int = 3, max_pending: int = 8, max_loss_gap_ns: int = 1_000_000_000):
        if history < 1 or not 0.0 <= quantile <= 1.0 or min_intervals < 1 or keep_gaps < 0 \
                or rate_change_intervals < 2 or max_pending < rate_change_intervals or max_loss_gap_ns <= 0:
            raise ValueError('StreamLoss: history >= 1, 0 <= quantile <= 1, min_intervals >= 1, keep_gaps >= 0, '
                             'rate_change_intervals >= 2, max_pending >= rate_change_intervals, max_loss_gap_ns > 0')
        self.quantile = quantile
        self.min_intervals = min_intervals
        self.rate_change_intervals = rate_change_intervals
        self.max_pending = max_pending
        self.max_loss_gap_ns = max_loss_gap_ns
        self._intervals: collections.deque[int] = collections.deque(maxlen=history)
        self._last_stamp_ns: int | None = None
        self._open_gaps: collections.deque[Gap] = collections.deque(maxlen=keep_gaps)   # with unmatched images
        self._pending: list[Gap] = []      # consecutive gaps waiting for the next interval
        self._early: list[int] = []        # intervals seen before the period was known (judged once it is)
        self._unmatched_reports = 0
        self._slow_run: list[int] = []     # consecutive long intervals without a sequence gap (a rate change?)
        self.sequence = PublicationSequence()
        self.lost_rmw = 0              # images the RMW reported lost
        self.lost_stamp_gap_only = 0   # confirmed missing images that no report accounts for
        self.lost_sequence_gap_only = 0   # images missing in the sequence numbers that no report accounts for
        self.gaps = 0                  # intervals with images counted missing
        self.unexplained_gaps = 0      # of them, not (yet) explained by reported losses
        self.rate_changes = 0          # times the frame period was re-estimated from a run of equal gaps
        self.stamp_jumps = 0           # forward stamp discontinuities (not counted as lost images)
        self.last_jump_ns = 0          # the stamp interval of the latest one

    # ------------------------------------------------------------------------------------------------ estimate
    @property
    def period_ns(self) -> int | None:
        """The estimated frame period (ns), None until `min_intervals` intervals were seen."""
        if len(self._intervals) < self.min_intervals:
            return None
        ordered = sorted(self._intervals)
        base = ordered[min(int(self.quantile * len(ordered)), len(ordered) - 1)]
        return int(round(statistics.median(i / max(1, round(i / base)) for i in ordered)))

    @property
    def lost_total(self) -> int:
        return self.lost_rmw + self.lost_stamp_gap_only + self.lost_sequence_gap_only

    # ------------------------------------------------------------------------------------------------ inputs
    def on_rmw_lost(self, count: int) -> None:
        """The middleware reported `count` more lost samples (rclpy's message-lost total_count_change)."""
        if count <= 0:
            return
        self.lost_rmw += count
        self._unmatched_reports += count
        # a report that comes after its gap was seen: a confirmed gap's images were counted as stamp-gap losses
        while self._unmatched_reports and self._open_gaps:
            gap = self._open_gaps[0]
            if gap.state == WITHDRAWN:
                self._open_gaps.popleft()
                continue
            n = min(gap.missing - gap.matched, self._unmatched_reports)
            self._match(gap, n)
            if gap.reported:
                self._open_gaps.popleft()

    def _match(self, gap: Gap, n: int) -> None:
        was_explained = gap.explained
        gap.matched += n
        self._unmatched_reports -= n
        if gap.by_sequence:
            self.lost_sequence_gap_only -= n
        elif gap.state == CONFIRMED:
            self.lost_stamp_gap_only -= n
            if gap.explained and not was_explained:
                self.unexplained_gaps -= 1
        elif gap.state == PENDING and gap.explained:   # the reports are the evidence: counted, no longer pending
            self._pending.remove(gap)
            self._confirm(gap)

    def _confirm(self, gap: Gap) -> None:
        gap.state = CONFIRMED
        self.gaps += 1
        self.lost_stamp_gap_only += gap.missing - gap.matched
        if not gap.explained:
            self.unexplained_gaps += 1

    def _confirm_pending(self) -> None:
        for gap in self._pending:
            self._confirm(gap)
        self._pending = []

    def _restart(self) -> None:
        """A new stream (time went backwards, a stamp jump): no period, nothing pending."""
        for gap in self._pending:
            gap.state = WITHDRAWN
        self._pending = []
        self._early = []
        self._slow_run = []
        self._intervals.clear()

    def _is_jump(self, interval_ns: int, period_ns: int) -> bool:
        """The one rule: an interval longer than max(max_loss_gap, JUMP_PERIODS frame periods) is a discontinuity of
        the stamps, not images lost in transport."""
        return interval_ns > max(self.max_loss_gap_ns, JUMP_PERIODS * period_ns)

    def on_sample(self, seq: int | None, source: str = '') -> None:
        """A sample that is not part of the stream arrived on its topic (an image of another camera, dropped): its
        publication sequence number still counts the samples lost before it (sequence numbers are the writer's,
        whatever the frame_id of each sample)."""
        missing = self.sequence.step(source, seq)
        if missing:
            self._sequence_gap(missing, 0, 0)

    def on_image(self, stamp_ns: int, seq: int | None = None, source: str = '') -> Gap | None:
        """An image with header stamp `stamp_ns` arrived, `seq` its publication sequence number (None, 0: unknown)
        on `source` (the caller's key for the writers it comes from: the subscription's topic); returns the Gap it
        ends (a stamp gap is pending until the stream around it confirms it), or None (no image missing, the first
        image, a period not known yet, a stamp jump, or time going backwards, which restarts the estimate)."""
        missing = self.sequence.step(source, seq)
        last, self._last_stamp_ns = self._last_stamp_ns, stamp_ns
        if last is None or stamp_ns <= last:
            if last is not None and stamp_ns < last:     # a restarted bag or simulator: a new stream
                self._restart()
            if missing:          # the numbers still count what was lost
                self._sequence_gap(missing, 0, 0)
            return None
        interval = stamp_ns - last
        if missing is not None:
            return self._on_sequenced(interval, missing)
        period = self.period_ns
        if period is not None and period > 0 and self._is_jump(interval, period) \
                and self._unmatched_reports < round(interval / period) - 1:
            self.stamp_jumps += 1
            self.last_jump_ns = interval
            self._confirm_pending()      # the images before the jump ran at the rate: their gaps were losses
            self._restart()
            return None
        self._intervals.append(interval)
        if period is None or period <= 0:
            self._early.append(interval)
            if self.period_ns:
                self._judge_early()
            return None
        multiple = round(interval / period)
        if interval < 1.5 * period or multiple < 2:
            self._confirm_pending()      # the camera still runs at the estimated rate
            return None
        gap = Gap(interval_ns=interval, period_ns=period, missing=int(multiple) - 1, state=PENDING)
        n = min(gap.missing, self._unmatched_reports)
        gap.matched = n
        self._unmatched_reports -= n
        if gap.explained:
            self._confirm(gap)
            return gap
        self._pending.append(gap)
        self._open_gaps.append(gap)
        self._judge_pending()
        return gap

    def _on_sequenced(self, interval: int, missing: int) -> Gap | None:
        """An interval whose images the sequence numbers account for (`missing` lost in it): a sequence gap, or
        none; the stamps still say whether the camera jumped (beyond what the missing images explain) or changed
        its rate (equal long intervals without a loss)."""
        period = self.period_ns
        if period and self._is_jump(interval - missing * period, period):     # beyond the missing images' time
            self.stamp_jumps += 1
            self.last_jump_ns = interval
            self._confirm_pending()
            self._restart()
            return self._sequence_gap(missing, interval, period) if missing else None
        self._intervals.append(interval // (missing + 1))
        if period and not missing and interval >= 1.5 * period:
            self._slow_run.append(interval)
            run = self._slow_run[-self.rate_change_intervals:]
            mid = statistics.median(run)
            if len(run) == self.rate_change_intervals and all(abs(i - mid) <= 0.15 * mid for i in run):
                self._intervals.clear()
                self._intervals.extend([int(mid)] * self.min_intervals)
                self.rate_changes += 1
                self._slow_run = []
        else:
            self._slow_run = []
            self._confirm_pending()     # stamp gaps from before the numbers were known: the camera runs at its rate
        return self._sequence_gap(missing, interval, period) if missing else None

    def _sequence_gap(self, missing: int, interval: int, period: int | None) -> Gap:
        """`missing` images lost in an interval of `interval` ns (0: not measurable), counted now and matched
        with the middleware's reports (earlier ones now, later ones as they come)."""
        period = period or (interval // (missing + 1))
        gap = Gap(interval_ns=interval, period_ns=period, missing=missing, by_sequence=True)
        n = min(missing, self._unmatched_reports)
        gap.matched = n
        self._unmatched_reports -= n
        self.gaps += 1
        self.lost_sequence_gap_only += missing - n
        if not gap.reported:
            self._open_gaps.append(gap)
        return gap

    def _judge_early(self) -> None:
        """The period just became known: the intervals before it are judged against it. The stream that gave the
        period runs at that rate, so their gaps are losses (confirmed, matched with reports where there are any);
        without this, images lost in the first `min_intervals` intervals of a stream would never be counted."""
        period = self.period_ns
        for interval in self._early:
            multiple = round(interval / period)
            if interval < 1.5 * period or multiple < 2 or self._is_jump(interval, period):
                continue
            gap = Gap(interval_ns=interval, period_ns=period, missing=int(multiple) - 1, state=PENDING)
            n = min(gap.missing, self._unmatched_reports)
            gap.matched = n
            self._unmatched_reports -= n
            self._confirm(gap)
            if not gap.reported:
                self._open_gaps.append(gap)
        self._early = []

    def _judge_pending(self) -> None:
        """A run of equal unreported gaps is a new rate (withdrawn, the period re-estimated); too many pending gaps
        of varying length are losses after all (heavy loss at the same rate)."""
        run = self._pending[-self.rate_change_intervals:]
        if len(run) == self.rate_change_intervals and all(g.matched == 0 for g in run):
            mid = statistics.median(g.interval_ns for g in run)
            if all(abs(g.interval_ns - mid) <= 0.15 * mid for g in run):
                for gap in self._pending:
                    if gap.matched == 0 and abs(gap.interval_ns - mid) <= 0.15 * mid:
                        gap.state = WITHDRAWN
                    else:
                        self._confirm(gap)
                self._pending = []
                self._intervals.clear()
                self._intervals.extend([int(mid)] * self.min_intervals)
                self.rate_changes += 1
                return
        while len(self._pending) > self.max_pending:
            self._confirm(self._pending.pop(0))

    def counts(self) -> dict:
        """The counters for /diagnostics (period in ms, 'n/a' until known)."""
        period = self.period_ns
        return {'lost.transport': self.lost_total, 'lost.rmw': self.lost_rmw,
                'lost.stamp_gaps_only': self.lost_stamp_gap_only,
                'lost.sequence_gaps_only': self.lost_sequence_gap_only, 'lost.gaps': self.gaps,
                'lost.unexplained_gaps': self.unexplained_gaps, 'input_rate_changes': self.rate_changes,
                'input_stamp_jumps': self.stamp_jumps, **self.sequence.counts(),
                'input_period_ms': round(period / 1e6, 3) if period else 'n/a'}
