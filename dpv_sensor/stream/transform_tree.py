"""A small TF tree without ROS: the latest transform of every frame to its parent, and the transform between any two
frames of one tree, chained through the frames between them (numpy, float64).

``set(parent, child, T_parent_child_44, static)`` stores a link as /tf_static or /tf carry it (a TransformStamped:
header.frame_id is the parent, child_frame_id the child, the transform maps child points to the parent). As in tf2
every frame has one parent: a link to a new parent replaces the old one. Only the latest transform of each link is
kept (no history: the node uses the current camera mount for the images that follow), a static link is not
replaced by a dynamic one of the same child, and at most ``max_frames`` links are held (the oldest dynamic ones go).

``lookup(target, source)`` returns ``T_target_source`` (maps points in `source` to `target`, tf2's
lookupTransform(target, source)): both frames are walked up to their roots, the chain meets at the first common
ancestor, and T_target_source = inv(T_ancestor_target) @ T_ancestor_source. When the frames are not connected the
answer says which link is missing. Frame names are compared without a leading '/'. Thread-safe.
"""
from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

MAX_DEPTH = 1000            # longest chain walked (tf2's limit): guards against a loop in bad input


@dataclass
class Lookup:
    """Answer of TransformTree.lookup: T_target_source, or None with the reason (which frames are unknown or
    not connected)."""
    T_target_source_44: np.ndarray | None
    reason: str = ''

    @property
    def ok(self) -> bool:
        return self.T_target_source_44 is not None


@dataclass
class _Link:
    parent: str
    T_parent_child: np.ndarray
    static: bool


def frame_name(name: str) -> str:
    """A frame name as tf2 compares it: without a leading '/'."""
    return (name or '').lstrip('/')


class TransformTree:
    """The latest transform of each child frame to its parent; lookups chain them (see the module doc)."""

    def __init__(self, max_frames: int = 1000):
        self.max_frames = int(max_frames)
        self._links: OrderedDict[str, _Link] = OrderedDict()
        self._lock = threading.Lock()
        self.updates = 0            # links stored (new or changed)

    def __len__(self) -> int:
        with self._lock:
            return len(self._links)

    def set(self, parent: str, child: str, T_parent_child_44, static: bool = False) -> bool:
        """Store the link parent -> child; False (ignored) for an empty or self link, a non-finite transform, or a
        dynamic transform of a child that has a static one."""
        parent, child = frame_name(parent), frame_name(child)
        T = np.asarray(T_parent_child_44, dtype=np.float64)
        if not parent or not child or parent == child or T.shape != (4, 4) or not np.all(np.isfinite(T)):
            return False
        with self._lock:
            old = self._links.get(child)
            if old is not None and old.static and not static:
                return False
            self._links[child] = _Link(parent, T.copy(), bool(static))
            self._links.move_to_end(child)
            self.updates += 1
            while len(self._links) > self.max_frames:
                oldest = next((k for k, v in self._links.items() if not v.static), next(iter(self._links)))
                del self._links[oldest]
        return True

    def _to_root(self, frame: str) -> list[tuple[str, np.ndarray]]:
        """[(ancestor, T_ancestor_frame)]: `frame` itself (identity) and each ancestor up to the root."""
        chain = [(frame, np.eye(4))]
        T = np.eye(4)
        seen = {frame}
        while len(chain) < MAX_DEPTH:
            link = self._links.get(chain[-1][0])
            if link is None or link.parent in seen:
                break
            T = link.T_parent_child @ T
            chain.append((link.parent, T))
            seen.add(link.parent)
        return chain

    def lookup(self, target: str, source: str) -> Lookup:
        """T_target_source through the tree (identity when the two are one frame)."""
        target, source = frame_name(target), frame_name(source)
        if not target or not source:
            return Lookup(None, 'empty frame name')
        if target == source:
            return Lookup(np.eye(4))
        with self._lock:
            up_source = self._to_root(source)
            up_target = self._to_root(target)
        at_target = {f: T for f, T in up_target}
        for ancestor, T_ancestor_source in up_source:
            T_ancestor_target = at_target.get(ancestor)
            if T_ancestor_target is not None:
                return Lookup(np.linalg.inv(T_ancestor_target) @ T_ancestor_source)
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
