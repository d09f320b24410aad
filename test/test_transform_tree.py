"""TransformTree (dpv_sensor.stream.transform_tree): chained lookups against answers worked out by hand; what counts
as another transform; loops through the path; links that publishers disagree on, each rule just either side of its
time threshold, with transforms that differ in rotation only.

The robot: base_link -> camera_link 0.2 m forward and 0.5 m up (no rotation), camera_link -> camera_optical turned
as REP 103 optical frames are (z forward = x of the link, x right = -y, y down = -z). A point 1 m in front of the
optical frame (0, 0, 1) is then 1.2 m forward and 0.5 m up of base_link: (1.2, 0, 0.5).
"""
import math

import numpy as np
import pytest

from dpv_sensor.stream import transform_tree as TT
from dpv_sensor.stream.transform_tree import TransformTree, frame_name, same_transform

# columns: the optical frame's x, y, z axes in camera_link (x right = -y_link, y down = -z_link, z forward = x_link)
R_LINK_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def pose(R=np.eye(3), t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def yaw(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])


def robot() -> TransformTree:
    tree = TransformTree()
    assert tree.set('base_link', 'camera_link', pose(t=(0.2, 0.0, 0.5)), static=True)
    assert tree.set('camera_link', 'camera_optical', pose(R_LINK_OPTICAL), static=True)
    return tree


def test_two_link_chain():
    T = robot().lookup('base_link', 'camera_optical')
    assert T.ok
    np.testing.assert_allclose(T.T_target_source_44 @ [0.0, 0.0, 1.0, 1.0], [1.2, 0.0, 0.5, 1.0], atol=1e-12)
    np.testing.assert_allclose(T.T_target_source_44, pose(R_LINK_OPTICAL, (0.2, 0.0, 0.5)), atol=1e-12)


def test_inverse_direction():
    T = robot().lookup('camera_optical', 'base_link').T_target_source_44
    # base_link's origin seen from the camera: 0.2 m behind (z -0.2) and 0.5 m below (y down +0.5)
    np.testing.assert_allclose(T @ [0.0, 0.0, 0.0, 1.0], [0.0, 0.5, -0.2, 1.0], atol=1e-12)
    np.testing.assert_allclose(T @ [1.2, 0.0, 0.5, 1.0], [0.0, 0.0, 1.0, 1.0], atol=1e-12)


def test_siblings_meet_at_the_common_parent_and_one_frame_is_identity():
    tree = robot()
    tree.set('base_link', 'lidar', pose(t=(0.0, 0.0, 1.0)), static=True)
    T = tree.lookup('lidar', 'camera_link').T_target_source_44
    np.testing.assert_allclose(T[:3, 3], [0.2, 0.0, -0.5], atol=1e-12)
    np.testing.assert_allclose(tree.lookup('/camera_link', 'camera_link').T_target_source_44, np.eye(4))
    assert frame_name('/base_link') == 'base_link'


def test_missing_link():
    tree = TransformTree()
    tree.set('camera_link', 'camera_optical', pose(R_LINK_OPTICAL), static=True)
    missing = tree.lookup('base_link', 'camera_optical')
    assert not missing.ok and "'base_link' not in the tree" in missing.reason
    tree.set('odom', 'base_link', pose(), static=False)
    apart = tree.lookup('base_link', 'camera_optical')
    assert not apart.ok and 'two unconnected trees' in apart.reason and "root 'camera_link'" in apart.reason
    tree.set('base_link', 'camera_link', pose(t=(0.2, 0.0, 0.5)))      # the missing link arrives
    assert tree.lookup('base_link', 'camera_optical').ok


def test_a_changing_dynamic_transform_gives_the_latest():
    tree = robot()
    tree.set('base_link', 'pan', pose(yaw(0.0)))
    tree.set('pan', 'cam2', pose(t=(1.0, 0.0, 0.0)))
    np.testing.assert_allclose(tree.lookup('base_link', 'cam2').T_target_source_44[:3, 3], [1.0, 0.0, 0.0])
    tree.set('base_link', 'pan', pose(yaw(90.0)))                       # the pan unit turned 90 deg left
    np.testing.assert_allclose(tree.lookup('base_link', 'cam2').T_target_source_44[:3, 3], [0.0, 1.0, 0.0],
                               atol=1e-12)


def test_bad_input_is_ignored_and_static_links_are_kept():
    tree = robot()
    assert not tree.set('base_link', 'camera_link', np.full((4, 4), np.nan))
    assert not tree.set('', 'x', pose()) and not tree.set('a', 'a', pose())
    assert not tree.set('base_link', 'camera_link', pose(t=(9.0, 9.0, 9.0)), static=False)   # static wins
    np.testing.assert_allclose(tree.lookup('base_link', 'camera_link').T_target_source_44[:3, 3], [0.2, 0.0, 0.5])
    loop = TransformTree()
    loop.set('a', 'b', pose(t=(1.0, 0.0, 0.0)))
    loop.set('b', 'a', pose(t=(1.0, 0.0, 0.0)))                          # a loop in bad input: no hang
    assert not loop.lookup('a', 'c').ok


def test_the_tree_holds_at_most_max_frames():
    tree = TransformTree(max_frames=3)
    tree.set('world', 'fixed', pose(), static=True)
    for i in range(5):
        tree.set('world', f'f{i}', pose())
    assert len(tree) == 3 and tree.lookup('world', 'fixed').ok and tree.lookup('world', 'f4').ok


def axis_angle(axis, rad: float) -> np.ndarray:
    """Rodrigues: the rotation by `rad` about `axis`."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    Kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(rad) * Kx + (1.0 - math.cos(rad)) * Kx @ Kx


MOUNT_T = (0.3, -0.4, 1.2)        # 1.3 m long: not a unit vector


def test_a_transform_that_turns_without_moving_is_another_one():
    """Rotation alone (the translation kept, 1.3 m long) and translation alone, each just either side of 1e-6."""
    A = pose(axis_angle((1.0, 2.0, 2.0), 0.4), MOUNT_T)
    for rad, same in ((2e-6, False), (0.5e-6, True)):
        turned = pose(A[:3, :3] @ axis_angle((0.0, 0.0, 1.0), rad), MOUNT_T)
        assert same_transform(A, turned) is same, rad
        assert same_transform(turned, A) is same, rad
    step = np.array([1.0, 2.0, 2.0]) / 3.0                       # a unit direction off the axes
    for metres, same in ((2e-6, False), (0.5e-6, True)):
        moved = pose(A[:3, :3], np.array(MOUNT_T) + metres * step)
        assert same_transform(A, moved) is same, metres
    assert not same_transform(A, pose(A[:3, :3] @ axis_angle((0.0, 1.0, 0.0), math.pi), MOUNT_T))   # half a turn


def chain_with(closing: np.ndarray | None) -> TransformTree:
    """base_link -> camera_link -> camera_optical on /tf_static, and optionally camera_optical -> base_link."""
    tree = robot()
    if closing is not None:
        assert tree.set('camera_optical', 'base_link', closing, static=True)
    return tree


def test_a_loop_through_the_path_gives_no_answer_and_names_its_frames():
    assert chain_with(None).lookup('base_link', 'camera_optical').ok
    tree = chain_with(pose(yaw(30.0), (0.5, 0.0, 0.0)))
    loop = ("'base_link' -> 'camera_link' -> 'camera_optical' -> 'base_link'")
    for target, source in (('base_link', 'camera_optical'), ('camera_optical', 'base_link'),
                           ('base_link', 'camera_link')):
        found = tree.lookup(target, source)
        assert not found.ok and found.loop == ('base_link', 'camera_link', 'camera_optical', 'base_link'), found
        assert found.reason == 'a loop in the tree: ' + loop


def test_a_loop_above_the_path_does_not_touch_the_answer():
    up = TransformTree()
    up.set('base_link', 'camera_link', pose(t=(0.2, 0.0, 0.5)), static=True)
    up.set('camera_link', 'camera_optical', pose(R_LINK_OPTICAL), static=True)
    up.set('map', 'base_link', pose())
    up.set('odom', 'map', pose())
    up.set('map', 'odom', pose())                                            # map <-> odom, above base_link
    found = up.lookup('base_link', 'camera_optical')
    assert found.ok and found.loop == () and found.conflicts == ()
    np.testing.assert_allclose(found.T_target_source_44, pose(R_LINK_OPTICAL, (0.2, 0.0, 0.5)), atol=1e-12)
    assert not up.lookup('map', 'camera_optical').ok                         # through the loop: none


A = pose(yaw(0.0), MOUNT_T)
B = pose(yaw(5.0), MOUNT_T)           # the same translation, turned 5 deg: only the rotation disagrees


def static_pair(dt_b: float) -> TransformTree:
    """camera_link on /tf_static: A at t=0, B `dt_b` s later (a second latched publisher, or an update)."""
    tree = TransformTree()
    tree.set('base_link', 'camera_link', A, static=True, now=0.0)
    tree.set('base_link', 'camera_link', B, static=True, now=dt_b)
    return tree


def mount(tree, now):
    found = tree.lookup('base_link', 'camera_link', now=now)
    return found.T_target_source_44, found.conflicts


def test_two_static_values_at_once_hold_the_first_until_the_conflict_clears():
    burst = TT.STATIC_BURST_S
    tree = static_pair(burst - 0.01)                       # within the burst: two publishers disagree
    T, conflicts = mount(tree, burst)
    np.testing.assert_allclose(T, A, atol=1e-12)
    (c,) = conflicts
    assert (c.child, c.parent, c.kind, c.events) == ('camera_link', 'base_link', 'values', 1)
    assert len(c.values) == 2 and same_transform(c.values[0][1], A) and same_transform(c.values[1][1], B)
    last = burst - 0.01
    T, conflicts = mount(tree, last + TT.CONFLICT_CLEAR_S - 0.01)
    assert conflicts and same_transform(T, A)              # still held just before it clears
    T, conflicts = mount(tree, last + TT.CONFLICT_CLEAR_S)
    assert conflicts == () and same_transform(T, B)        # then the latest, as tf2
    T, conflicts = mount(static_pair(burst), burst)        # a change a burst later: an update, followed
    assert conflicts == () and same_transform(T, B)


def test_static_publishers_taking_turns_are_a_conflict_held_at_the_value_before():
    tree = TransformTree()
    tree.set('base_link', 'camera_link', A, static=True, now=0.0)
    tree.set('base_link', 'camera_link', B, static=True, now=5.0)          # one change: followed
    T, conflicts = mount(tree, 5.0)
    assert conflicts == () and same_transform(T, B)
    t = 5.0
    for i in range(6):                                                      # then A, B, A, ... every 0.25 s
        t += 0.25
        tree.set('base_link', 'camera_link', A if i % 2 == 0 else B, static=True, now=t)
    T, conflicts = mount(tree, t)
    (c,) = conflicts
    assert same_transform(T, A) and c.since == 5.0 and c.events == 6 and c.kind == 'values'
    tree.set('base_link', 'camera_link', B, static=True, now=t + 1.0)      # repeats are no new evidence
    assert mount(tree, t + 1.0)[1][0].events == 6


@pytest.mark.parametrize('gap,conflict', [(TT.FLIP_MEMORY_S - 0.01, True), (TT.FLIP_MEMORY_S + 0.01, False)])
def test_a_return_counts_within_the_flip_memory(gap, conflict):
    tree = TransformTree()
    tree.set('base_link', 'camera_link', A, static=True, now=0.0)
    tree.set('base_link', 'camera_link', B, static=True, now=100.0)        # A left at 100 s
    tree.set('base_link', 'camera_link', A, static=True, now=100.0 + gap)
    T, conflicts = mount(tree, 100.0 + gap)
    assert bool(conflicts) is conflict and same_transform(T, A)


def test_a_moving_joint_on_tf_is_followed_not_a_conflict():
    tree = TransformTree()
    for i in range(8):                                   # a pan unit jittering between two encoder steps at 50 Hz
        tree.set('base_link', 'pan', B if i % 2 else A, now=i * 0.02)
    found = tree.lookup('base_link', 'pan', now=0.2)
    assert found.conflicts == () and same_transform(found.T_target_source_44, B)


def test_conflicting_parents_hold_the_parent_before():
    tree = TransformTree()
    tree.set('base_link', 'camera_link', pose(t=(0.2, 0.0, 0.5)), static=True, now=0.0)
    tree.set('camera_link', 'camera_optical', pose(R_LINK_OPTICAL), static=True, now=0.0)
    tree.set('mast', 'camera_link', pose(t=(0.0, 0.0, 0.1)), static=True, now=5.0)     # re-parented: followed
    assert not tree.lookup('base_link', 'camera_optical', now=5.0).ok                  # mast is not under base_link
    tree.set('base_link', 'camera_link', pose(t=(0.2, 0.0, 0.5)), static=True, now=5.5)  # back: two publishers
    tree.set('mast', 'camera_link', pose(t=(0.0, 0.0, 0.1)), static=True, now=6.0)
    found = tree.lookup('base_link', 'camera_optical', now=6.0)
    assert found.ok and [(c.child, c.parent, c.kind, c.events) for c in found.conflicts] == \
        [('camera_link', 'base_link', 'parents', 2)]
    np.testing.assert_allclose(found.T_target_source_44, pose(R_LINK_OPTICAL, (0.2, 0.0, 0.5)), atol=1e-12)
    # a /tf parent that contradicts the /tf_static one: ignored (static wins), and a conflict
    other = robot()
    assert not other.set('odom', 'camera_link', pose(), static=False, now=1.0)
    assert other.conflict('camera_link', now=1.0).kind == 'parents'
    assert other.conflict('camera_link', now=1.0 + TT.CONFLICT_CLEAR_S) is None
