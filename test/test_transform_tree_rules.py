"""TransformTree (dpv_sensor.stream.transform_tree): the conflict rules and the loop rule, each case just either side
of its documented threshold with the values written out (never taken from the module's constants, so a wrong
constant fails here):

- a link that returns to a value (a /tf_static transform, or a parent) it left within 30 s: two publishers take
  turns, a conflict held at the returning value (FLIP_MEMORY_S, measured from when that value *left*);
- a /tf_static link that changes again less than 1 s after its last change: two latched publishers (STATIC_BURST_S);
- a conflict lasts until 10 s pass without new evidence (CONFLICT_CLEAR_S);
- a link remembers its 4 earlier values (HISTORY);
- a loop through a frame of the lookup's path gives no answer, wherever the path enters it.
"""
import math

import numpy as np
import pytest

from dpv_sensor.stream.transform_tree import TransformTree, same_transform

MOUNT_T = (0.3, -0.4, 1.2)


def mount(deg: float) -> np.ndarray:
    """The camera mount turned `deg` about z (the same translation): values that differ in rotation only."""
    a = math.radians(deg)
    T = np.eye(4)
    T[:3, :3] = [[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = MOUNT_T
    return T


A, B, C, D, E, F = (mount(d) for d in (0.0, 5.0, 10.0, 15.0, 20.0, 25.0))


def static_sequence(values, parent='base_link'):
    """camera_link on /tf_static: each (time, T) in turn."""
    tree = TransformTree()
    for now, T in values:
        assert tree.set(parent, 'camera_link', T, static=True, now=now)
    return tree


def seen(tree, now):
    """(T_base_link_camera_link the lookups use, the conflict or None) at `now`."""
    found = tree.lookup('base_link', 'camera_link', now=now)
    assert found.ok, found.reason
    return found.T_target_source_44, tree.conflict('camera_link', now=now)


@pytest.mark.parametrize('away_s, conflict', [
    (29.99, True),          # A left 29.99 s ago and returns: within the 30 s memory, two publishers take turns
    (30.0, True),           # 30 s exactly: still within
    (30.01, False),         # just beyond: an update back to an old value
    (20.0, True),
    (3.5, True),
    (65.0, False),
])
def test_a_static_value_that_returns_within_30_s_is_a_conflict(away_s, conflict):
    tree = static_sequence([(0.0, A), (100.0, B), (100.0 + away_s, A)])        # A left at 100 s
    T, c = seen(tree, 100.0 + away_s)
    assert same_transform(T, A)                     # held at A, or A as the latest value: A either way
    assert (c is not None) is conflict, away_s
    if conflict:
        assert c.kind == 'values' and c.since == 100.0 and c.events == 1
        assert same_transform(c.held[1], A)
        T, c = seen(tree, 100.0 + away_s + 0.5)
        assert same_transform(T, A) and c is not None


def test_two_static_publishers_taking_turns_every_20_s_are_seen():
    """A and B in turn every 20 s (slower than any burst, within the 30 s memory): after the first change, every
    return is a conflict, since the returning value left 20 s before (each clears 10 s later, before the next)."""
    tree = static_sequence([(0.0, A), (20.0, B)])
    T, c = seen(tree, 20.0)
    assert c is None and same_transform(T, B)       # one change: followed
    for now, value in ((40.0, A), (60.0, B), (80.0, A), (100.0, B)):
        tree.set('base_link', 'camera_link', value, static=True, now=now)
        T, c = seen(tree, now)
        assert c is not None and c.kind == 'values' and c.since == now - 20.0, now
        assert same_transform(c.held[1], value) and same_transform(T, value)


@pytest.mark.parametrize('b_at, conflict', [
    (35.0, False),          # A left at 35 s: 65 s before it returns at 100 s; C only arrived 5 s before
    (69.99, False),         # A left 30.01 s before its return
    (70.0, True),           # A left 30 s before its return
    (75.0, True),           # A left 25 s before its return
])
def test_the_memory_counts_from_when_the_earlier_value_left(b_at, conflict):
    """A (0 s), B, C (95 s), then A again at 100 s: whether A's return is a conflict depends on when A left (when
    B came), not on how long the current value C has lasted (5 s)."""
    tree = static_sequence([(0.0, A), (b_at, B), (95.0, C), (100.0, A)])
    T, c = seen(tree, 100.0)
    assert (c is not None) is conflict, b_at
    assert same_transform(T, A)
    if conflict:
        assert c.since == b_at and same_transform(c.held[1], A)
    else:
        assert seen(tree, 101.0)[1] is None


@pytest.mark.parametrize('b_at, conflict', [(35.0, False), (75.0, True)])
def test_a_parent_that_returns_counts_from_when_it_was_left(b_at, conflict):
    """The same rule for parents (on /tf): base_link (0 s), mast, arm (95 s), base_link again at 100 s."""
    tree = TransformTree()
    for now, parent in ((0.0, 'base_link'), (b_at, 'mast'), (95.0, 'arm'), (100.0, 'base_link')):
        assert tree.set(parent, 'camera_link', A, now=now)
    c = tree.conflict('camera_link', now=100.0)
    assert (c is not None) is conflict, b_at
    if conflict:
        assert c.kind == 'parents' and c.parent == 'base_link' and c.since == b_at


@pytest.mark.parametrize('away_s, conflict', [(29.99, True), (30.01, False)])
def test_a_dynamic_parent_that_returns_within_30_s_is_a_conflict(away_s, conflict):
    tree = TransformTree()
    tree.set('base_link', 'camera_link', A, now=0.0)
    tree.set('mast', 'camera_link', A, now=100.0)
    tree.set('base_link', 'camera_link', A, now=100.0 + away_s)
    c = tree.conflict('camera_link', now=100.0 + away_s)
    assert (c is not None) is conflict
    if conflict:
        assert c.kind == 'parents' and c.parent == 'base_link'


@pytest.mark.parametrize('dt, conflict', [
    (0.0, True),            # two latched publishers at once
    (0.99, True),           # within 1 s of the last change
    (1.0, False),           # 1 s exactly: an update
    (1.01, False),
])
def test_a_static_value_that_changes_within_1_s_is_a_burst(dt, conflict):
    tree = static_sequence([(10.0, A), (10.0 + dt, B)])
    T, c = seen(tree, 10.0 + dt)
    assert (c is not None) is conflict, dt
    assert same_transform(T, A if conflict else B)       # held at the value before, else the update followed


@pytest.mark.parametrize('dt, conflict', [(0.99, True), (1.0, False)])
def test_a_static_parent_that_changes_within_1_s_is_a_burst(dt, conflict):
    tree = TransformTree()
    tree.set('base_link', 'camera_link', A, static=True, now=10.0)
    tree.set('mast', 'camera_link', A, static=True, now=10.0 + dt)
    c = tree.conflict('camera_link', now=10.0 + dt)
    assert (c is not None) is conflict, dt
    if conflict:
        assert c.kind == 'parents' and c.parent == 'base_link'


def test_a_dynamic_value_that_changes_within_1_s_is_a_moving_joint():
    tree = TransformTree()
    tree.set('base_link', 'camera_link', A, now=10.0)
    tree.set('base_link', 'camera_link', B, now=10.01)
    tree.set('base_link', 'camera_link', A, now=10.02)         # and back: a joint moving, on /tf
    T, c = seen(tree, 10.02)
    assert c is None and same_transform(T, A)


@pytest.mark.parametrize('after_s, held', [
    (0.0, True),
    (9.99, True),           # under 10 s after the last disagreeing message: still held at A
    (10.0, False),          # 10 s exactly: over, the latest value (B) counts
    (10.01, False),
])
def test_a_conflict_clears_10_s_after_its_last_evidence(after_s, held):
    tree = static_sequence([(0.0, A), (0.5, B)])                # a burst at 0.5 s: held at A
    T, c = seen(tree, 0.5 + after_s)
    assert (c is not None) is held, after_s
    assert same_transform(T, A if held else B)


def test_new_evidence_within_10_s_extends_the_conflict_and_after_10_s_starts_a_new_one():
    tree = static_sequence([(0.0, A), (0.5, B), (9.0, A)])      # A returns 8.5 s after leaving: a second event
    c = tree.conflict('camera_link', now=9.0)
    assert c.events == 2 and c.since == 0.0
    assert tree.conflict('camera_link', now=18.99) is not None  # 9.99 s after the last event
    assert tree.conflict('camera_link', now=19.0) is None
    tree.set('base_link', 'camera_link', B, static=True, now=25.0)   # B returns, 16 s after it left (9 s)
    c = tree.conflict('camera_link', now=25.0)
    assert c is not None and c.events == 1 and c.since == 9.0       # a new conflict, not the old one's 3rd event


@pytest.mark.parametrize('returns_at, events, since', [
    (10.49, 2, 0.0),        # 9.99 s after the last evidence (0.5 s): the running conflict's second event
    (10.5, 1, 0.5),         # 10 s exactly: that one is over, a new conflict starts (A left at 0.5 s)
])
def test_evidence_10_s_after_the_last_starts_a_new_conflict(returns_at, events, since):
    tree = static_sequence([(0.0, A), (0.5, B), (returns_at, A)])
    c = tree.conflict('camera_link', now=returns_at)
    assert c is not None and (c.events, c.since) == (events, since)


def test_only_the_links_of_the_path_below_the_common_ancestor_report_their_conflicts():
    """camera_link and imu both under base_link; base_link under odom, whose /tf_static link has a burst (a
    conflict on base_link's link). The lookup between the camera and the IMU meets at base_link and never uses
    that link: no conflict; a lookup to or from odom uses it: the conflict is reported."""
    tree = TransformTree()
    J = np.eye(4)
    J[0, 3] = 1.0
    tree.set('base_link', 'camera_link', A, static=True, now=0.0)
    tree.set('base_link', 'imu', B, static=True, now=0.0)
    tree.set('odom', 'base_link', np.eye(4), static=True, now=0.0)
    tree.set('odom', 'base_link', J, static=True, now=0.2)
    assert tree.conflict('base_link', now=0.5) is not None
    assert tree.lookup('camera_link', 'imu', now=0.5).conflicts == ()
    assert [c.child for c in tree.lookup('odom', 'camera_link', now=0.5).conflicts] == ['base_link']
    assert [c.child for c in tree.lookup('camera_link', 'odom', now=0.5).conflicts] == ['base_link']   # either way


@pytest.mark.parametrize('values, conflict', [
    ((A, B, C, D, E), True),        # A is 4 values back: remembered
    ((A, B, C, D, E, F), False),    # 5 values back: forgotten, an update
])
def test_a_link_remembers_its_four_earlier_values(values, conflict):
    """Changes 2 s apart (no burst), all within 30 s, then A again."""
    tree = static_sequence([(2.0 * i, T) for i, T in enumerate(values)] + [(2.0 * len(values), A)])
    c = tree.conflict('camera_link', now=2.0 * len(values))
    assert (c is not None) is conflict


def test_a_loop_the_path_enters_below_its_start_frames_gives_no_answer():
    """odom published with base_link as its parent as well as base_link with odom (a second odometry node): the
    loop base_link <-> odom holds the common ancestor of camera_optical and imu, though neither of them is in it.
    The lookup says so at once instead of walking the loop to tf2's 1000-link limit and answering."""
    tree = TransformTree()
    tree.set('base_link', 'camera_link', mount(0.0), static=True, now=0.0)
    tree.set('camera_link', 'camera_optical', mount(90.0), static=True, now=0.0)
    tree.set('base_link', 'imu', mount(30.0), static=True, now=0.0)
    tree.set('odom', 'base_link', mount(45.0), now=0.0)
    assert tree.lookup('camera_optical', 'imu', now=0.0).ok
    tree.set('base_link', 'odom', mount(45.0), now=0.0)
    for target, source in (('camera_optical', 'imu'), ('imu', 'camera_optical'), ('camera_link', 'imu')):
        found = tree.lookup(target, source, now=0.0)
        assert not found.ok, (target, source)
        assert found.loop == ('base_link', 'odom', 'base_link'), found
        assert found.reason == "a loop in the tree: 'base_link' -> 'odom' -> 'base_link'"


def test_a_loop_two_links_above_the_start_frames_is_found():
    """camera_optical -> camera_link -> base_link -> odom -> map -> base_link, and imu under odom: the loop
    base_link, odom, map holds the common ancestor (odom) of camera_optical and imu, two and one links above them."""
    tree = TransformTree()
    tree.set('camera_link', 'camera_optical', mount(90.0), static=True, now=0.0)
    tree.set('base_link', 'camera_link', mount(0.0), static=True, now=0.0)
    tree.set('odom', 'base_link', mount(0.0), now=0.0)
    tree.set('odom', 'imu', mount(0.0), now=0.0)
    tree.set('map', 'odom', mount(0.0), now=0.0)
    tree.set('base_link', 'map', mount(0.0), now=0.0)
    assert tree.lookup('camera_link', 'camera_optical', now=0.0).ok     # its path misses the loop
    found = tree.lookup('camera_optical', 'imu', now=0.0)
    assert not found.ok and found.loop == ('base_link', 'map', 'odom', 'base_link'), found


def test_the_frames_evicted_first_are_the_least_recently_updated():
    """At most 2 links: a, b, then a changes (its link is now the newest), then c: b goes, not a."""
    tree = TransformTree(max_frames=2)
    tree.set('w', 'a', A, now=0.0)
    tree.set('w', 'b', A, now=1.0)
    tree.set('w', 'a', B, now=2.0)
    tree.set('w', 'c', A, now=3.0)
    assert tree.lookup('w', 'a', now=3.0).ok and tree.lookup('w', 'c', now=3.0).ok
    assert not tree.lookup('w', 'b', now=3.0).ok


@pytest.mark.parametrize('links, ok', [(999, True), (1000, False)])
def test_a_chain_is_walked_up_to_1000_frames(links, ok):
    """tf2's limit: a chain of 999 links (1000 frames) is walked, its 1 cm steps adding up to 9.99 m; with one
    more link the walk stops short of the root and the two ends are not connected."""
    tree = TransformTree(max_frames=5000)
    step = np.eye(4)
    step[0, 3] = 0.01
    for i in range(links):
        tree.set(f'f{i}', f'f{i + 1}', step, now=0.0)
    found = tree.lookup('f0', f'f{links}', now=0.0)
    assert found.ok is ok, found.reason
    if ok:
        assert found.T_target_source_44[0, 3] == pytest.approx(0.01 * links)


def test_a_dynamic_update_of_a_static_link_is_ignored_and_only_another_parent_is_a_conflict():
    tree = static_sequence([(0.0, A)])
    assert not tree.set('base_link', 'camera_link', B, static=False, now=1.0)    # same parent: ignored, no conflict
    T, c = seen(tree, 1.0)
    assert c is None and same_transform(T, A)
    assert not tree.set('mast', 'camera_link', B, static=False, now=2.0)         # another parent: a conflict
    T, c = seen(tree, 2.0)
    assert c is not None and c.kind == 'parents' and same_transform(T, A)


def test_a_static_value_that_was_earlier_on_tf_is_not_a_return():
    """A on /tf at 0 s, then B on /tf_static at 10 s, then A on /tf_static at 15 s: A was never a /tf_static value of
    the link, so its return is a plain change (no conflict; A counts)."""
    tree = TransformTree()
    tree.set('base_link', 'camera_link', A, static=False, now=0.0)
    tree.set('base_link', 'camera_link', B, static=True, now=10.0)
    tree.set('base_link', 'camera_link', A, static=True, now=15.0)
    T, c = seen(tree, 15.0)
    assert c is None and same_transform(T, A)


def test_a_returning_parent_counts_from_when_it_was_last_left():
    """camera_link's /tf parent: base_link (0 s), mast (1 s), base_link (2 s), mast (3 s): a conflict that clears
    10 s after its last evidence (3 s); at 14 s base_link returns, last left at 3 s (and first at 1 s): a new
    conflict since 3 s."""
    tree = TransformTree()
    for now, parent in ((0.0, 'base_link'), (1.0, 'mast'), (2.0, 'base_link'), (3.0, 'mast'), (14.0, 'base_link')):
        tree.set(parent, 'camera_link', A, now=now)
    c = tree.conflict('camera_link', now=14.0)
    assert c is not None and c.kind == 'parents' and c.since == 3.0 and c.events == 1
