"""Images lost between the camera and the node: counted from gaps in the header stamps and from the middleware's
message-lost reports, each lost image once. Pure Python (no rclpy).

The camera's frame period is estimated from the stamps of the images that arrive: a low quantile of the recent
intervals picks an interval of one period even when many images are lost (a median would pick two or more), and
the period is then the median of every recent interval divided by its whole number of periods. An interval of
`n` periods (n >= 2, rounded; 1.5 periods and more) means `n - 1` images are missing.

Two sources, one count: the RMW (rclpy's message-lost event, where the middleware reports it: Fast DDS does for
best-effort readers from the sequence numbers) says *how many* samples were lost; the stamps say *where*. Each
missing image in a stamp gap is matched with a reported loss when one is unmatched (in either order: the event
may be handled before or after the image that ends the gap), so

    lost_total = lost_rmw + lost_stamp_gap_only

where ``lost_stamp_gap_only`` are missing images no report accounts for (a reliable reader, a middleware that does
not report, or images the camera driver itself never sent) and ``lost_rmw`` includes reports no gap shows (the
stamps were irregular, or the stream ended).

A gap counts as *transport loss* (:attr:`Gap.explained`) once every image missing in it is matched with a
reported loss: the camera kept running, so the camera stream's own gap is one period (:attr:`Gap.camera_gap_ns`),
and a consumer that restarts on stream interruptions should not restart for it. Gaps the reports do not
explain keep their stamp interval (a camera or driver that stalled looks the same in the stamps).
"""
from __future__ import annotations

import collections
import statistics
from dataclasses import dataclass


@dataclass
class Gap:
    """One interval in the stamps with images missing in it (updated when late loss reports match it)."""
    interval_ns: int     # the stamp interval between the two images received
    period_ns: int       # the estimated frame period at the time
    missing: int         # images missing in it (>= 1)
    matched: int = 0     # of them, matched with losses the RMW reported

    @property
    def explained(self) -> bool:
        """Every missing image is a loss the middleware reported (the camera did not stall)."""
        return self.matched >= self.missing

    @property
    def camera_gap_ns(self) -> int:
        """The gap of the camera stream itself: one period when the loss is explained, else the stamp interval."""
        return self.period_ns if self.explained else self.interval_ns


class StreamLoss:
    """Counts images lost in a camera stream (see the module docs). Not thread-safe: call from one thread.

    history: how many recent intervals the period estimate uses; quantile: the low quantile that picks a
    one-period interval; min_intervals: intervals needed before gaps are counted (earlier gaps are not counted);
    keep_gaps: how many recent unexplained gaps late loss reports may still match."""

    def __init__(self, history: int = 64, quantile: float = 0.1, min_intervals: int = 8, keep_gaps: int = 16):
        if history < 1 or not 0.0 <= quantile <= 1.0 or min_intervals < 1 or keep_gaps < 0:
            raise ValueError('StreamLoss: history >= 1, 0 <= quantile <= 1, min_intervals >= 1, keep_gaps >= 0')
        self.quantile = quantile
        self.min_intervals = min_intervals
        self._intervals: collections.deque[int] = collections.deque(maxlen=history)
        self._last_stamp_ns: int | None = None
        self._open_gaps: collections.deque[Gap] = collections.deque(maxlen=keep_gaps)   # with unmatched images
        self._unmatched_reports = 0
        self.lost_rmw = 0              # images the RMW reported lost
        self.lost_stamp_gap_only = 0   # images missing in the stamps that no report accounts for
        self.gaps = 0                  # intervals with images missing
        self.unexplained_gaps = 0      # of them, not (yet) explained by reported losses

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
        return self.lost_rmw + self.lost_stamp_gap_only

    # ------------------------------------------------------------------------------------------------ inputs
    def on_rmw_lost(self, count: int) -> None:
        """The middleware reported `count` more lost samples (rclpy's message-lost total_count_change)."""
        if count <= 0:
            return
        self.lost_rmw += count
        self._unmatched_reports += count
        # a report that comes after its gap was seen: the gap's images were counted as stamp-gap losses
        while self._unmatched_reports and self._open_gaps:
            gap = self._open_gaps[0]
            n = min(gap.missing - gap.matched, self._unmatched_reports)
            was_explained = gap.explained
            gap.matched += n
            self._unmatched_reports -= n
            self.lost_stamp_gap_only -= n
            if gap.explained:
                self._open_gaps.popleft()
                if not was_explained:
                    self.unexplained_gaps -= 1

    def on_image(self, stamp_ns: int) -> Gap | None:
        """An image with header stamp `stamp_ns` arrived; returns the Gap it ends, or None (no image missing, the
        first image, a period not known yet, or time going backwards, which restarts the estimate)."""
        last, self._last_stamp_ns = self._last_stamp_ns, stamp_ns
        if last is None:
            return None
        if stamp_ns <= last:
            if stamp_ns < last:     # a restarted bag or simulator: a new stream
                self._intervals.clear()
            return None
        interval = stamp_ns - last
        period = self.period_ns
        self._intervals.append(interval)
        if period is None or period <= 0:
            return None
        multiple = round(interval / period)
        if interval < 1.5 * period or multiple < 2:
            return None
        gap = Gap(interval_ns=interval, period_ns=period, missing=int(multiple) - 1)
        self.gaps += 1
        gap.matched = min(gap.missing, self._unmatched_reports)
        self._unmatched_reports -= gap.matched
        self.lost_stamp_gap_only += gap.missing - gap.matched
        if not gap.explained:
            self.unexplained_gaps += 1
            self._open_gaps.append(gap)
        return gap

    def counts(self) -> dict:
        """The counters for /diagnostics (period in ms, 'n/a' until known)."""
        period = self.period_ns
        return {'lost.transport': self.lost_total, 'lost.rmw': self.lost_rmw,
                'lost.stamp_gaps_only': self.lost_stamp_gap_only, 'lost.gaps': self.gaps,
                'lost.unexplained_gaps': self.unexplained_gaps,
                'input_period_ms': round(period / 1e6, 3) if period else 'n/a'}
