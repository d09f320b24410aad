"""Where the worker's time goes, for /diagnostics: the share of wall time it was busy processing images, and the
median time of each estimator stage over the last keyframes. A node that drops images as ``busy`` then says whether
it is starved (busy nearly all the time) and by which stage. No ROS import; the worker feeds it, the diagnostics
read it."""
from __future__ import annotations

import collections
import statistics
import threading
from typing import Deque, Dict, Optional, Tuple

__all__ = ['WorkerLoad']


class WorkerLoad:
    """``busy(start, end)`` records one image's processing (monotonic seconds); ``keyframe(timings_ms)`` one
    keyframe's stage timings (``DepthOutput.timings_ms``). ``busy_share(now, window_s)``: the share of the last
    ``window_s`` seconds spent processing (None before a whole window has passed since the first image);
    ``stage_medians()``: the median of each top-level stage (no ``stage.part`` keys) over the last ``keyframes``."""

    def __init__(self, keyframes: int = 50):
        self._spans: Deque[Tuple[float, float]] = collections.deque()
        self._stages: Deque[Dict[str, float]] = collections.deque(maxlen=keyframes)
        self._first: Optional[float] = None
        self._lock = threading.Lock()

    def busy(self, start: float, end: float) -> None:
        with self._lock:
            if self._first is None:
                self._first = start
            self._spans.append((start, end))

    def keyframe(self, timings_ms: Dict[str, float]) -> None:
        with self._lock:
            self._stages.append({k: float(v) for k, v in timings_ms.items() if '.' not in k})

    def busy_share(self, now: float, window_s: float) -> Optional[float]:
        with self._lock:
            if self._first is None or now - self._first < window_s:
                return None
            start = now - window_s
            while self._spans and self._spans[0][1] <= start:
                self._spans.popleft()
            busy = sum(min(e, now) - max(s, start) for s, e in self._spans if e > start and s < now)
            return max(0.0, min(1.0, busy / window_s))

    def stage_medians(self) -> Dict[str, float]:
        with self._lock:
            stages = list(self._stages)
        keys = []
        for t in stages:
            keys += [k for k in t if k not in keys]
        return {k: statistics.median([t[k] for t in stages if k in t]) for k in keys}

    def text(self) -> str:
        """The stage medians as /diagnostics shows them: 'stage ms, ...' in the estimator's order, the total last."""
        med = self.stage_medians()
        parts = [f'{k} {v:.0f}' for k, v in med.items() if k != 'total']
        if 'total' in med:
            parts.append(f"total {med['total']:.0f}")
        return ', '.join(parts) if parts else 'n/a'
