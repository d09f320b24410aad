"""A small TF tree without ROS: the latest transform of every frame to its parent, and the transform between any two
frames of one tree, chained through the frames between them (numpy, float64); loops and links that two publishers
disagree on are detected.

``set(parent, child, T_parent_child_44, static)`` stores a link as /tf_static or /tf carry it (a TransformStamped:
header.frame_id is the parent, child_frame_id the child, the transform maps child points to the parent). As in tf2
every frame has one parent: a link to a new parent replaces the old one. Only the latest transform of each link is
kept (no history: the node uses the current camera mount for the images that follow), a static link is not
replaced by a dynamic one of the same child, and at most ``max_frames`` links are held (the oldest dynamic ones go).

``lookup(target, source)`` returns ``T_target_source`` (maps points in `source` to `target`, tf2's
lookupTransform(target, source)): both frames are walked up to their roots, the chain meets at the first common
ancestor, and T_target_source = inv(T_ancestor_target) @ T_ancestor_source. When the frames are not connected the
answer says which link is missing. Frame names are compared without a leading '/'. Thread-safe.

Faults of the tree (the answer names them; what to do about them is the caller's):
- a loop (a frame that is its own ancestor, e.g. base_link -> camera_link -> camera_optical plus camera_optical ->
  base_link) through a frame of the lookup's path: there is no answer (``Lookup.loop`` lists the loop's frames);
- a conflict on a link: two publishers that disagree on it, seen as a link that returns to a parent it had within
  ``FLIP_MEMORY_S`` (kind 'parents'; also a /tf parent that contradicts the /tf_static one), or a /tf_static link
  that returns to a transform it had within ``FLIP_MEMORY_S`` or changes less than ``STATIC_BURST_S`` after its last
  change (kind 'values': latched publishers that disagree arrive together). A /tf transform that changes is a
  moving joint, never a conflict. While a conflict lasts (until ``CONFLICT_CLEAR_S`` pass without new evidence) the
  link is held at the value it had before the disagreement began, and every lookup through it lists it in
  ``Lookup.conflicts``; then the latest value counts again, as in tf2.
Times are seconds on one monotonic clock (``now``; time.monotonic() when not given).
"""
from __future__ import annotations

import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field, replace

import numpy as np

MAX_DEPTH = 1000            # longest chain walked (tf2's limit): guards against a loop in bad input
SAME_M = 1e-6               # two transforms whose translations differ less than this (and whose rotations differ
SAME_ROT = 1e-6             # less than this: largest element of R_a^T R_b - I, about the angle in radians) are one
STATIC_BURST_S = 1.0        # a /tf_static link that changes again within this: two latched publishers disagree
FLIP_MEMORY_S = 30.0        # a link that returns to a value it left within this: two publishers take turns
CONFLICT_CLEAR_S = 10.0     # a conflict is over after this long without new evidence
HISTORY = 4                 # earlier values kept per link (for returns)


def same_transform(A_44, B_44) -> bool:
    """True when the two rigid transforms differ by less than SAME_M in translation and SAME_ROT in rotation (a
    transform that turns without moving is another transform)."""
    A, B = np.asarray(A_44), np.asarray(B_44)
    return bool(np.linalg.norm(A[:3, 3] - B[:3, 3]) <= SAME_M and
                np.max(np.abs(A[:3, :3].T @ B[:3, :3] - np.eye(3))) <= SAME_ROT)


@dataclass
class Conflict:
    """Two publishers disagree on the link `parent` -> `child`: `kind` 'parents' (the child is given two parents) or
    'values' (two transforms on /tf_static); `values` the (parent, T_parent_child) seen since it began, `held` the
    one the lookups use meanwhile (the link before the disagreement), `events` the disagreeing messages so far,
    `since` / `last` the times of the first and the latest."""
    child: str
    kind: str
    held: tuple
    values: list = field(default_factory=list)
    since: float = 0.0
    last: float = 0.0
    events: int = 0

    @property
    def parent(self) -> str:
        return self.held[0]


@dataclass
class Lookup:
    """Answer of TransformTree.lookup: T_target_source, or None with the reason (which frames are unknown or
    not connected)."""
    T_target_source_44: np.ndarray | None
    reason: str = ''
    loop: tuple = ()            # a loop through the path: its frames, parent before child, the first one repeated
    conflicts: tuple = ()       # Conflict of each link of the path that is held (the answer uses the held values)

    @property
    def ok(self) -> bool:
        return self.T_target_source_44 is not None


@dataclass
class _Link:
    parent: str
    T_parent_child: np.ndarray
    static: bool
    since: float = 0.0          # when this value arrived (a change; repeats of it do not move it)
    earlier: list = field(default_factory=list)     # [(parent, T, static, left_at)] values it had before, newest last


def frame_name(name: str) -> str:
    """A frame name as tf2 compares it: without a leading '/'."""
    return (name or '').lstrip('/')


class TransformTree:
    """The latest transform of each child frame to its parent; lookups chain them (see the module doc)."""

    def __init__(self, max_frames: int = 1000):
        self.max_frames = int(max_frames)
        self._links: OrderedDict[str, _Link] = OrderedDict()
        self._conflicts: dict[str, Conflict] = {}
        self._lock = threading.Lock()
        self.updates = 0            # links stored (new or changed)

    def __len__(self) -> int:
        with self._lock:
            return len(self._links)

    def set(self, parent: str, child: str, T_parent_child_44, static: bool = False, now: float | None = None) -> bool:
        """Store the link parent -> child; False (ignored) for an empty or self link, a non-finite transform, or a
        dynamic transform of a child that has a static one (a conflict when it names another parent)."""
        parent, child = frame_name(parent), frame_name(child)
        T = np.asarray(T_parent_child_44, dtype=np.float64)
        if not parent or not child or parent == child or T.shape != (4, 4) or not np.all(np.isfinite(T)):
            return False
        now = time.monotonic() if now is None else float(now)
        with self._lock:
            old = self._links.get(child)
            if old is not None and old.static and not static:
                if old.parent != parent:
                    self._evidence(child, 'parents', (old.parent, old.T_parent_child), (parent, T), now, now)
                return False
            if old is not None and old.parent == parent and same_transform(old.T_parent_child, T):
                old.T_parent_child, old.static = T.copy(), bool(static)        # a repeat: the value stays
            else:
                earlier = []
                if old is not None:
                    self._judge_change(child, old, parent, T, static, now)
                    earlier = (old.earlier + [(old.parent, old.T_parent_child, old.static, now)])[-HISTORY:]
                self._links[child] = _Link(parent, T.copy(), bool(static), now, earlier)
            self._links.move_to_end(child)
            self.updates += 1
            while len(self._links) > self.max_frames:
                oldest = next((k for k, v in self._links.items() if not v.static), next(iter(self._links)))
                del self._links[oldest]
                self._conflicts.pop(oldest, None)
        return True

    def _judge_change(self, child: str, old: _Link, parent: str, T: np.ndarray, static: bool, now: float) -> None:
        """A link changes from `old` to (parent, T): evidence of a conflict (see the module doc) or a plain change."""
        recent = [e for e in old.earlier if now - e[3] <= FLIP_MEMORY_S]
        if parent != old.parent:
            back = [e for e in recent if e[0] == parent]
            if back:                                    # the child returns to a parent it had: held at that one
                self._evidence(child, 'parents', (parent, T), (old.parent, old.T_parent_child), back[-1][3], now)
            elif static and old.static and now - old.since < STATIC_BURST_S:
                self._evidence(child, 'parents', (old.parent, old.T_parent_child), (parent, T), old.since, now)
            return
        if not (static and old.static):
            return                                      # a moving joint on /tf
        back = [e for e in recent if e[0] == parent and e[2] and same_transform(e[1], T)]
        if back:
            self._evidence(child, 'values', (parent, T), (old.parent, old.T_parent_child), back[-1][3], now)
        elif now - old.since < STATIC_BURST_S:
            self._evidence(child, 'values', (old.parent, old.T_parent_child), (parent, T), old.since, now)

    def _evidence(self, child: str, kind: str, held: tuple, other: tuple, since: float, now: float) -> None:
        """One disagreeing message on `child`: a new conflict held at `held`, or one more event of a running one."""
        c = self._conflicts.get(child)
        if c is None or now - c.last >= CONFLICT_CLEAR_S:
            c = self._conflicts[child] = Conflict(child, kind, (held[0], held[1].copy()), since=since)
        if kind == 'parents':
            c.kind = 'parents'
        for value in (held, other):
            if not any(v[0] == value[0] and same_transform(v[1], value[1]) for v in c.values):
                c.values.append((value[0], value[1].copy()))
        del c.values[:-HISTORY]
        c.last = now
        c.events += 1

    def conflict(self, child: str, now: float | None = None) -> Conflict | None:
        """The conflict on `child`'s link while it lasts, else None."""
        now = time.monotonic() if now is None else float(now)
        with self._lock:
            return self._active(frame_name(child), now)

    def _active(self, child: str, now: float) -> Conflict | None:
        c = self._conflicts.get(child)
        if c is not None and now - c.last >= CONFLICT_CLEAR_S:
            del self._conflicts[child]
            return None
        return c

    def _to_root(self, frame: str, now: float) -> tuple[list[tuple[str, np.ndarray]], tuple]:
        """([(ancestor, T_ancestor_frame)]: `frame` itself (identity) and each ancestor up to the root, held links
        at their held value; the loop met on the way (its frames, parent first, the first repeated) or ())."""
        chain = [(frame, np.eye(4))]
        T = np.eye(4)
        seen = [frame]
        while len(chain) < MAX_DEPTH:
            child = chain[-1][0]
            link = self._links.get(child)
            if link is None:
                break
            held = self._active(child, now)
            parent, T_parent_child = held.held if held is not None else (link.parent, link.T_parent_child)
            if parent in seen:
                cycle = seen[seen.index(parent):][::-1]         # parent before child
                first = cycle.index(min(cycle))
                cycle = cycle[first:] + cycle[:first]
                return chain, tuple(cycle + [cycle[0]])
            T = T_parent_child @ T
            chain.append((parent, T))
            seen.append(parent)
        return chain, ()

    def lookup(self, target: str, source: str, now: float | None = None) -> Lookup:
        """T_target_source through the tree (identity when the two are one frame); None with the loop when a loop
        runs through a frame of the path; the held conflicts of the path's links."""
        target, source = frame_name(target), frame_name(source)
        if not target or not source:
            return Lookup(None, 'empty frame name')
        if target == source:
            return Lookup(np.eye(4))
        now = time.monotonic() if now is None else float(now)
        with self._lock:
            up_source, loop_source = self._to_root(source, now)
            up_target, loop_target = self._to_root(target, now)
            at_target = {f: (i, T) for i, (f, T) in enumerate(up_target)}
            for i, (ancestor, T_ancestor_source) in enumerate(up_source):
                if ancestor in at_target:
                    j, T_ancestor_target = at_target[ancestor]
                    path = [f for f, _ in up_source[:i + 1]] + [f for f, _ in up_target[:j]]
                    loop = next((c for c in (loop_source, loop_target) if set(c) & set(path)), ())
                    if loop:
                        return Lookup(None, 'a loop in the tree: ' + ' -> '.join(f"'{f}'" for f in loop), loop=loop)
                    links = [f for f, _ in up_source[:i]] + [f for f, _ in up_target[:j]]
                    held = tuple(replace(c, values=list(c.values)) for c in (self._active(f, now) for f in links)
                                 if c is not None)           # copies: the tree goes on changing its own
                    return Lookup(np.linalg.inv(T_ancestor_target) @ T_ancestor_source, conflicts=held)
        return Lookup(None, self._why_unconnected(target, source, up_target[-1][0], up_source[-1][0]))

    def _why_unconnected(self, target: str, source: str, target_root: str, source_root: str) -> str:
        known = self.frames()
        missing = [f for f in (target, source) if f not in known]
        if missing:
            return f"frame {' and '.join(repr(f) for f in missing)} not in the tree ({len(known)} frames known)"
        return (f"'{target}' (root '{target_root}') and '{source}' (root '{source_root}') are in two unconnected "
                'trees')

    def frames(self) -> set[str]:
        """Every frame named by a link (children and parents)."""
        with self._lock:
            return set(self._links) | {link.parent for link in self._links.values()}
