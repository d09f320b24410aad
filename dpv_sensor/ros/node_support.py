"""Small plumbing pieces of the node, without ROS: the one-slot mailbox between the callback thread and the worker (and
what its replaced images are counted as while the worker waits for odometry), a rate meter, the fault log (per-kind
counters and rate-limited messages), the one logging bridge from Python logging to the node's logger, and the record
of a received image."""
from __future__ import annotations

import collections
import logging
import threading
import time
from dataclasses import dataclass, field

__all__ = ['Mailbox', 'OdometryWait', 'RateMeter', 'FaultLog', 'LogBridge', 'Incoming', 'merge_incoming', 'max_gap',
           'camera_gap_ns', 'plausible_age_ms']


class Mailbox:
    """One-slot hand-over from the callback thread to the worker: a newer item replaces a waiting one.

    merge: optional `merge(dropped_item, new_item) -> item` called (under the lock) when a waiting item is replaced,
    so the new item can inherit what the dropped one knew (the node carries the stream's longest image gap)."""

    def __init__(self, merge=None):
        self._item = None
        self._cv = threading.Condition()
        self._merge = merge
        self.replaced = 0
        self.closed = False

    def put(self, item) -> bool:
        """Store `item`; returns True when it replaced (dropped) an item the worker had not taken yet."""
        with self._cv:
            dropped = self._item is not None
            if dropped:
                self.replaced += 1
                if self._merge is not None:
                    item = self._merge(self._item, item)
            self._item = item
            self._cv.notify()
            return dropped

    def take(self, timeout: float):
        """The waiting item (removing it), or None after `timeout` s / when closed."""
        with self._cv:
            if self._item is None and not self.closed:
                self._cv.wait(timeout)
            item, self._item = self._item, None
            return item

    def close(self) -> None:
        with self._cv:
            self.closed = True
            self._cv.notify_all()


class OdometryWait:
    """Whether the worker is waiting for odometry after an image's stamp, and the images replaced in the mailbox
    meanwhile: the worker could not take them because the odometry was late, which the end of the wait tells (it
    timed out: the odometry cause; the odometry came in time: the usual busy worker). Images replaced while the worker
    computes are busy at once. Thread-safe (the callback thread replaces, the worker waits)."""

    def __init__(self):
        self._lock = threading.Lock()
        self._waiting = False
        self._held = 0           # images replaced during the current wait

    @property
    def waiting(self) -> bool:
        return self._waiting

    def replaced(self) -> bool:
        """An image was replaced: True when it is counted now (busy), False when it is held for the wait's end."""
        with self._lock:
            if self._waiting:
                self._held += 1
            return not self._waiting

    def start(self) -> None:
        with self._lock:
            self._waiting = True

    def end(self) -> int:
        """The wait ended: the images replaced during it (to count by how it ended)."""
        with self._lock:
            n, self._held, self._waiting = self._held, 0, False
            return n


class RateMeter:
    """Events per second over a sliding window of monotonic times."""

    def __init__(self, window_s: float = 5.0):
        self.window_s = window_s
        self._t: collections.deque[float] = collections.deque()
        self._lock = threading.Lock()

    def tick(self, t: float | None = None) -> None:
        with self._lock:
            self._t.append(time.monotonic() if t is None else t)
            self._trim()

    def _trim(self):
        now = time.monotonic()
        while self._t and now - self._t[0] > self.window_s:
            self._t.popleft()

    def rate(self) -> float:
        with self._lock:
            self._trim()
            if len(self._t) < 2:
                return 0.0
            span = max(self._t[-1] - self._t[0], 1e-6)
            return (len(self._t) - 1) / span

    def last(self) -> float | None:
        with self._lock:
            return self._t[-1] if self._t else None

    def mean_rate(self, since: float | None = None) -> float:
        """Events in the window over the window's length (or over the time since `since`, a monotonic time, when
        that is shorter): unlike :meth:`rate` it falls to 0 when the events stop."""
        with self._lock:
            self._trim()
            span = self.window_s if since is None else min(self.window_s, time.monotonic() - since)
            return len(self._t) / span if span > 0 else 0.0


class FaultLog:
    """Per-kind counters and rate-limited log messages.

    Messages are limited per key (the kind, or a finer key such as 'image_size_change:640x480->320x240'): at most
    `burst` messages per key in any `period_s` window; the ones held back are counted and the number is appended to
    the next message of that key that gets through.
    """

    def __init__(self, logger, period_s: float = 5.0, burst: int = 3):
        self.logger = logger
        self.period_s = period_s
        self.burst = burst
        self.counts: collections.Counter = collections.Counter()
        self._recent: dict[str, collections.deque] = {}
        self._suppressed: collections.Counter = collections.Counter()
        self._lock = threading.Lock()

    def count(self, kind: str, n: int = 1) -> None:
        """Count `n` faults of `kind` without a message (one was logged already)."""
        with self._lock:
            self.counts[kind] += n

    def report(self, kind: str, message: str, level: str = 'warn', count: bool = True, key: str | None = None,
               period_s: float | None = None) -> bool:
        """Count one fault of `kind` and log `message` unless rate-limited; returns True when it was logged.
        `period_s` overrides the limiter window for this key."""
        now = time.monotonic()
        key = key or kind
        period = self.period_s if period_s is None else period_s
        with self._lock:
            if count:
                self.counts[kind] += 1
            recent = self._recent.setdefault(key, collections.deque())
            while recent and now - recent[0] >= period:
                recent.popleft()
            if len(recent) >= self.burst:
                self._suppressed[key] += 1
                return False
            recent.append(now)
            suppressed, self._suppressed[key] = self._suppressed[key], 0
        if suppressed:
            message += f' ({suppressed} more like this were not logged)'
        # one call site per severity: rclpy loggers refuse a severity change at the same call site
        if level == 'error':
            self.logger.error(message)
        elif level == 'info':
            self.logger.info(message)
        else:
            self.logger.warning(message)
        return True


class LogBridge(logging.Handler):
    """The one logging bridge: Python logging records of dpv_sensor.* (the estimator, the pose source, ...) ->
    the node's rclpy logger. ``attach()`` / ``detach()`` add and remove it on the ``dpv_sensor`` logger."""

    def __init__(self, rcl_logger):
        super().__init__(level=logging.INFO)
        self._log = rcl_logger

    def emit(self, record):
        try:
            msg = f'[{record.name}] {record.getMessage()}'
            if record.levelno >= logging.ERROR:
                self._log.error(msg)
            elif record.levelno >= logging.WARNING:
                self._log.warning(msg)
            else:
                self._log.info(msg)
        except Exception:  # logging must never raise into the algorithm
            pass

    def attach(self) -> 'LogBridge':
        root = logging.getLogger('dpv_sensor')
        root.addHandler(self)
        root.setLevel(logging.INFO)
        return self

    def detach(self) -> None:
        logging.getLogger('dpv_sensor').removeHandler(self)


def max_gap(a: int | None, b: int | None) -> int | None:
    """The larger of two image gaps (ns); None = unknown, ignored."""
    return b if a is None else a if b is None else max(a, b)


@dataclass
class Incoming:
    msg: object          # sensor_msgs/Image as received
    receipt_mono: float  # time.monotonic() at receipt
    receipt_ns: int      # wall clock (ns) at receipt
    gap_ns: int | None = None  # longest stamp interval between consecutive received images up to this one, since
    #                            the previous item the worker took (None: first image, or time went backwards)
    loss_gaps: list = field(default_factory=list)  # stream_loss.Gap of the intervals with images lost in transport
    #                            (their interval is not in gap_ns: see camera_gap_ns)


def merge_incoming(dropped: Incoming, new: Incoming) -> Incoming:
    """Mailbox merge: the image replacing a dropped one inherits the dropped one's stream gap and lost intervals."""
    new.gap_ns = max_gap(dropped.gap_ns, new.gap_ns)
    new.loss_gaps = dropped.loss_gaps + new.loss_gaps
    return new


def camera_gap_ns(gap_ns: int | None, loss_gaps) -> int | None:
    """The camera stream's longest gap: the longest stamp interval between received images `gap_ns`, and the
    intervals with images lost in transport (`loss_gaps`, stream_loss.Gap), each of which counts as one frame period
    once the middleware reported all of its images lost (the camera kept running; ``Gap.camera_gap_ns``), else as
    its stamp interval. Read it as late as possible: the report may be handled after the image that ends the gap."""
    for lost in loss_gaps:
        gap_ns = max_gap(gap_ns, lost.camera_gap_ns)
    return gap_ns


PLAUSIBLE_AGE_NS = 3600 * 1_000_000_000
PLAUSIBLE_FUTURE_NS = 1_000_000_000


def plausible_age_ms(now_ns: int, stamp_ns: int) -> float | None:
    """The age (ms) of a header stamp on the node's clock, or None when it says nothing about latency: the clock
    reads zero (use_sim_time before /clock arrives), the stamp is more than an hour older (not on this clock: a bag
    written from stamp 0, a replay without use_sim_time) or more than a second in the future of the clock (a
    simulator's /clock behind its stamps or paused)."""
    if now_ns <= 0:
        return None
    age = now_ns - stamp_ns
    return age / 1e6 if -PLAUSIBLE_FUTURE_NS <= age <= PLAUSIBLE_AGE_NS else None
