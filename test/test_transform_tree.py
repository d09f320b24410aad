"""TransformTree (dpv_sensor.stream.transform_tree): chained lookups against answers worked out by hand.

The robot: base_link -> camera_link 0.2 m forward and 0.5 m up (no rotation), camera_link -> camera_optical turned
as REP 103 optical frames are (z forward = x of the link, x right = -y, y down = -z). A point 1 m in front of the
optical frame (0, 0, 1) is then 1.2 m forward and 0.5 m up of base_link: (1.2, 0, 0.5).
"""
import math

import numpy as np

from dpv_sensor.stream.transform_tree import TransformTree, frame_name

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
