"""The publication sequence numbers of a topic's samples: how many samples of a publisher never reached the callback.
Pure Python (no rclpy): the subscription callback passes the numbers in.

A DDS writer numbers its samples 1, 2, 3, ...; the middleware hands the number of each received sample to the
callback (rclpy's message info, 'publication_sequence_number'). A step from n to n + k means k - 1 samples of that
writer were lost before the callback, whatever dropped them (the writer's history overflowing under a reliable
reader, the reader's history overflowing before the callback took the samples, the network under best effort) and
whatever their stamps say. The numbers are followed per *source* (the caller's key: the subscription, as rclpy
does not say which writer sent a sample; one writer numbers every sample it sends, whatever its frame_id). Two
writers on one topic interleave their numbers, which then go back again and again. The numbers say nothing (None):

- where the middleware gives none (0, or the 'unsupported' value: all ones),
- for the first sample of a source,
- when the number goes back or repeats (a restarted publisher, or two publishers under one key), and for the
  `trust_after` steps after that: only a run of forward steps shows one publisher again.
"""
from __future__ import annotations

import collections

UNSUPPORTED = (1 << 63)     # numbers from here on are the middleware's 'unknown' (RMW_..._UNSUPPORTED = 2**64 - 1)


def known(seq) -> bool:
    """True when `seq` is a usable publication sequence number."""
    return isinstance(seq, int) and 0 < seq < UNSUPPORTED


class PublicationSequence:
    """Per-source publication sequence numbers (see the module docs). Not thread-safe: call from one thread.

    trust_after: forward steps needed after a number went back before gaps count again; max_sources: sources
    followed at once (the least recently seen is forgotten)."""

    def __init__(self, trust_after: int = 8, max_sources: int = 16):
        if trust_after < 0 or max_sources < 1:
            raise ValueError('PublicationSequence: trust_after >= 0, max_sources >= 1')
        self.trust_after = trust_after
        self.max_sources = max_sources
        self._last: collections.OrderedDict[str, list[int]] = collections.OrderedDict()   # source -> [seq, trust]
        self.restarts = 0          # numbers that went back or repeated (a publisher restarted, or two publishers)
        self.unavailable = 0       # samples without a usable number
        self.last_restart: tuple[str, int, int] | None = None     # (source, previous number, new number)

    def step(self, source: str, seq) -> int | None:
        """A sample of `source` numbered `seq` arrived: how many samples of it were lost since its previous one, or
        None when the numbers cannot say (see the module docs)."""
        if not known(seq):
            self.unavailable += 1
            return None
        entry = self._last.get(source)
        if entry is None:
            self._last[source] = [seq, 0]
            while len(self._last) > self.max_sources:
                self._last.popitem(last=False)
            return None
        self._last.move_to_end(source)
        previous, waiting = entry
        entry[0] = seq
        if seq <= previous:
            self.restarts += 1
            self.last_restart = (source, previous, seq)
            entry[1] = self.trust_after
            return None
        if waiting > 0:
            entry[1] = waiting - 1
            return None
        return seq - previous - 1

    def counts(self) -> dict:
        return {'input_sequence_restarts': self.restarts}
