"""PoseBuffer: interpolation at image stamps against hand-computed answers, and every reason it can refuse."""
import math

import numpy as np
import pytest

from dpv_sensor.stream import pose_buffer as pb
from dpv_sensor.stream.pose_buffer import PoseBuffer

S = pb.NS  # one second in ns


def yaw(deg: float, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    a = math.radians(deg)
    T = np.eye(4)
    T[:3, :3] = [[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]]
    T[:3, 3] = t
    return T


def translation(x, y, z) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = [x, y, z]
    return T


def test_midpoint_of_a_pure_translation():
    buf = PoseBuffer(max_gap_s=1.0)
    buf.add(10 * S, translation(0.0, 0.0, 0.0))
    buf.add(10 * S + S // 2, translation(1.0, -2.0, 4.0))
    q = buf.pose_at(10 * S + S // 4)
    assert q.ok and q.reason is None
    np.testing.assert_allclose(q.T_world_cam_44, translation(0.5, -1.0, 2.0), atol=1e-12)


def test_quarter_of_the_way_is_a_quarter_of_the_translation():
    buf = PoseBuffer(max_gap_s=1.0)
    buf.add(0, translation(0.0, 0.0, 0.0))
    buf.add(S // 2, translation(4.0, 0.0, 0.0))
    np.testing.assert_allclose(buf.pose_at(S // 8).T_world_cam_44[:3, 3], [1.0, 0.0, 0.0], atol=1e-12)


def test_halfway_through_a_90_degree_yaw_is_45_degrees():
    buf = PoseBuffer(max_gap_s=1.0)
    buf.add(0, yaw(0.0))
    buf.add(S // 10, yaw(90.0, t=(2.0, 0.0, 0.0)))
    T = buf.pose_at(S // 20).T_world_cam_44
    c = math.sqrt(0.5)
    np.testing.assert_allclose(T[:3, :3], [[c, -c, 0], [c, c, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [1.0, 0.0, 0.0], atol=1e-12)


def test_slerp_is_not_a_linear_matrix_blend():
    # A third of the way through a 90 deg yaw is exactly 30 deg (a linear blend of matrices would not be a
    # rotation at all).
    buf = PoseBuffer(max_gap_s=1.0)
    buf.add(0, yaw(0.0))
    buf.add(3 * S // 10, yaw(90.0))
    np.testing.assert_allclose(buf.pose_at(S // 10).T_world_cam_44, yaw(30.0), atol=1e-12)


def test_shortest_arc_across_the_quaternion_sign_flip():
    # 170 deg -> -170 deg yaw: halfway is 180 deg, not 0 deg.
    buf = PoseBuffer(max_gap_s=1.0)
    buf.add(0, yaw(170.0))
    buf.add(S // 10, yaw(-170.0))
    np.testing.assert_allclose(buf.pose_at(S // 20).T_world_cam_44, yaw(180.0), atol=1e-12)


def test_exact_stamp_returns_the_message_itself():
    buf = PoseBuffer()
    buf.add(0, yaw(10.0))
    buf.add(S // 10, yaw(20.0, t=(1, 2, 3)))
    np.testing.assert_allclose(buf.pose_at(S // 10).T_world_cam_44, yaw(20.0, t=(1, 2, 3)), atol=1e-12)
    np.testing.assert_allclose(buf.pose_at(0).T_world_cam_44, yaw(10.0), atol=1e-12)


def test_static_T_base_camera_is_composed_on_the_right():
    T_base_cam = pb.pose7_to_matrix([0.1, 0.0, 0.2, 0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4)])
    buf = PoseBuffer(T_base_camera_44=T_base_cam)
    buf.add(0, translation(1.0, 0.0, 0.0))
    buf.add(S // 10, translation(1.0, 0.0, 0.0))
    T = buf.pose_at(S // 20).T_world_cam_44
    # camera 0.1 m forward (x) and 0.2 m up (z) of a base at x=1, turned 90 deg about z
    np.testing.assert_allclose(T[:3, 3], [1.1, 0.0, 0.2], atol=1e-12)
    np.testing.assert_allclose(T[:3, :3], yaw(90.0)[:3, :3], atol=1e-12)
    np.testing.assert_allclose(buf.base_pose_at(S // 20).T_world_cam_44, translation(1.0, 0.0, 0.0), atol=1e-12)


def test_future_stamp_says_future():
    buf = PoseBuffer()
    assert buf.pose_at(5 * S).reason == pb.FUTURE          # empty: wait for odometry
    buf.add(0, np.eye(4))
    q = buf.pose_at(1)
    assert not q.ok and q.reason == pb.FUTURE and 'newest odometry' in q.detail


def test_stamp_before_the_buffer_says_too_old():
    buf = PoseBuffer()
    buf.add(2 * S, np.eye(4))
    buf.add(3 * S, np.eye(4))
    assert buf.pose_at(S).reason == pb.TOO_OLD


def test_history_is_bounded_and_old_stamps_become_too_old():
    buf = PoseBuffer(history_s=1.0, max_gap_s=1.0)
    for k in range(101):                   # 10 s of odometry at 10 Hz
        buf.add(k * S // 10, translation(k, 0, 0))
    assert len(buf) <= 12                  # ~1 s kept, memory flat
    assert buf.pose_at(S).reason == pb.TOO_OLD
    np.testing.assert_allclose(buf.pose_at(9 * S + S // 20).T_world_cam_44[:3, 3], [90.5, 0, 0], atol=1e-9)


def test_bracket_wider_than_max_gap_says_gap():
    buf = PoseBuffer(max_gap_s=0.5)
    buf.add(0, np.eye(4))
    buf.add(S, np.eye(4))
    q = buf.pose_at(S // 2)
    assert q.reason == pb.GAP and 'exceeds max_odom_gap' in q.detail
    buf2 = PoseBuffer(max_gap_s=0.5)
    buf2.add(0, np.eye(4))
    buf2.add(S // 2, np.eye(4))            # exactly max_gap: still fine
    assert buf2.pose_at(S // 4).ok


def test_invalid_sample_gives_nan_for_the_stamps_it_brackets_only():
    buf = PoseBuffer(max_gap_s=1.0)
    buf.add(0, np.eye(4))
    bad = np.eye(4)
    bad[0, 3] = np.nan
    buf.add(S // 10, bad)
    buf.add(2 * S // 10, np.eye(4))
    buf.add(3 * S // 10, np.eye(4))
    assert buf.pose_at(S // 20).reason == pb.NAN
    assert buf.pose_at(3 * S // 20).reason == pb.NAN
    assert buf.pose_at(5 * S // 20).ok
    buf.add(4 * S // 10, None)             # None also marks an invalid message
    assert buf.pose_at(7 * S // 20).reason == pb.NAN
    skewed = np.eye(4)
    skewed[:3, :3] *= 1.1                  # not a rotation
    buf.add(5 * S // 10, skewed)
    assert buf.pose_at(9 * S // 20).reason == pb.NAN


def test_time_going_backwards_clears_the_buffer():
    buf = PoseBuffer(max_gap_s=1.0)
    for k in range(5):
        assert buf.add(100 * S + k * S // 10, translation(k, 0, 0)) is None
    msg = buf.add(S, translation(7, 0, 0))
    assert msg is not None and 'went backwards' in msg
    assert buf.epoch == 1 and len(buf) == 1
    assert buf.pose_at(100 * S).reason == pb.FUTURE       # the old timeline is gone
    buf.add(S + S // 10, translation(8, 0, 0))
    np.testing.assert_allclose(buf.pose_at(S + S // 20).T_world_cam_44[:3, 3], [7.5, 0, 0], atol=1e-12)


def test_odometry_teleport_clears_the_buffer():
    buf = PoseBuffer(max_gap_s=1.0, max_speed=10.0, max_rate_deg=720.0)
    for k in range(10):                                  # 100 Hz at 5 m/s: 5 cm per message, no jump
        assert buf.add(k * S // 100, translation(0.05 * k, 0, 0)) is None
    msg = buf.add(10 * S // 100, translation(0.05 * 9 + 0.5, 0, 0))   # 0.5 m in 10 ms
    assert msg is not None and 'jumped 0.500 m in 0.010 s' in msg
    assert buf.jumps == 1 and buf.epoch == 0 and len(buf) == 1
    assert buf.pose_at(5 * S // 100).reason == pb.TOO_OLD          # never interpolated across the teleport
    buf.add(11 * S // 100, translation(1.0, 0, 0))
    assert buf.pose_at(105 * S // 1000).ok
    # a turn of 30 degrees in 10 ms (3000 deg/s) is one too; 5 degrees in 10 ms is under the 10 degree floor
    assert buf.add(12 * S // 100, yaw(5.0, (1.0, 0, 0))) is None
    assert 'deg in 0.010 s' in buf.add(13 * S // 100, yaw(35.0, (1.0, 0, 0)))
    assert buf.jumps == 2
    # 5 cm of jitter at 1 kHz (50 m/s) is under the 0.1 m floor; off (0) means no check at all
    assert buf.add(1301 * S // 10000, yaw(35.0, (1.05, 0, 0))) is None
    off = PoseBuffer(max_gap_s=1.0)
    off.add(0, translation(0, 0, 0))
    assert off.add(S // 100, translation(100, 0, 0)) is None and off.jumps == 0


def test_small_reordering_is_tolerated_when_allowed():
    buf = PoseBuffer(max_gap_s=1.0, backwards_tolerance_s=0.05)
    buf.add(0, translation(0, 0, 0))
    buf.add(S // 10, translation(2, 0, 0))
    assert buf.add(S // 20, translation(1, 0, 0)) is None   # late by 50 ms: inserted in order
    assert buf.epoch == 0 and len(buf) == 3
    np.testing.assert_allclose(buf.pose_at(3 * S // 40).T_world_cam_44[:3, 3], [1.5, 0, 0], atol=1e-12)


def test_discard_newer_than():
    buf = PoseBuffer()
    for k in range(5):
        buf.add(k * S, np.eye(4))
    assert buf.discard_newer_than(2 * S) == 2
    assert buf.newest_ns == 2 * S


def test_quaternion_helpers_round_trip():
    rng = np.random.default_rng(0)
    for _ in range(50):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        R = pb.quat_to_matrix(q)
        q2 = pb.matrix_to_quat(R)
        assert np.allclose(q2, q) or np.allclose(q2, -q)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    T = pb.pose7_to_matrix([1, 2, 3, 0, 0, 0, 1])
    np.testing.assert_allclose(T, translation(1, 2, 3))
    np.testing.assert_allclose(pb.matrix_to_pose7(yaw(90.0, (1, 2, 3))),
                               [1, 2, 3, 0, 0, math.sqrt(0.5), math.sqrt(0.5)], atol=1e-12)
    with pytest.raises(ValueError):
        pb.pose7_to_matrix([0, 0, 0])


def test_a_second_message_at_one_stamp_keeps_the_first_and_says_whether_it_conflicts():
    buf = PoseBuffer(max_gap_s=1.0)
    assert buf.add(0, translation(0.0, 0.0, 0.0)) is None
    assert buf.add(S, translation(1.0, 0.0, 0.0)) is None
    # an identical repeat (a republished message): ignored, counted as a duplicate, no conflict
    assert buf.add(S, translation(1.0, 0.0, 0.0)) is None
    assert (buf.duplicates, buf.conflicts, buf.last_conflict) == (1, 0, None)
    # the same stamp 5 cm off: a conflict, the first pose stays
    assert buf.add(S, translation(1.05, 0.0, 0.0)) is None
    assert (buf.duplicates, buf.conflicts) == (1, 1)
    assert buf.last_conflict == 'conflicting odometry at 1.000 s: two poses 0.050 m and 0.0 deg apart'
    np.testing.assert_allclose(buf.pose_at(S // 2).T_world_cam_44, translation(0.5, 0.0, 0.0), atol=1e-12)
    np.testing.assert_allclose(buf.pose_at(S).T_world_cam_44, translation(1.0, 0.0, 0.0), atol=1e-12)
    # a rotation alone conflicts too; an invalid repeat of a valid sample conflicts; the buffer keeps 2 samples
    assert buf.add(S, yaw(1.0, t=(1.0, 0.0, 0.0))) is None and buf.conflicts == 2
    assert buf.last_conflict.endswith('0.000 m and 1.0 deg apart')
    assert buf.add(S, None) is None and buf.conflicts == 3 and 'invalid' in buf.last_conflict
    assert len(buf) == 2 and buf.epoch == 0


def test_a_repeated_stamp_after_time_went_backwards_is_a_new_stream():
    # a restarted bag repeats stamps the buffer still holds, but after newer ones: time went backwards, not a
    # conflict
    buf = PoseBuffer(max_gap_s=1.0)
    buf.add(0, translation(0.0, 0.0, 0.0))
    buf.add(S, translation(1.0, 0.0, 0.0))
    assert 'went backwards' in buf.add(0, translation(5.0, 0.0, 0.0))
    assert buf.conflicts == 0 and buf.epoch == 1 and len(buf) == 1


def test_one_teleport_rule_for_odometry_and_offline_steps():
    """continuity.teleport, the rule the pose buffer applies between odometry messages and the estimator between
    pushed frames: a step no camera can make in the time, never fast but smooth motion."""
    from dpv_sensor.stream.continuity import teleport
    assert 'odom_max_speed 10 m/s' in teleport(1 / 30, 0.5, 0.0, 10.0, 720.0)     # 15 m/s
    assert teleport(1 / 30, 0.3, 0.0, 10.0, 720.0) is None                         # 9 m/s
    assert teleport(1.5, 2.25, 0.0, 10.0, 720.0) is None                           # a 1.5 m/s walk, 1.5 s apart
    assert teleport(1.5, 0.0, 135.0, 10.0, 720.0) is None                          # a 90 deg/s pan, 1.5 s apart
    assert teleport(0.1, 0.0, 9.0, 10.0, 720.0) is None                            # 90 deg/s, 0.1 s apart
    assert 'odom_max_rate_deg 720' in teleport(1 / 30, 0.0, 30.0, 10.0, 720.0)   # 900 deg/s
    assert teleport(0.001, 0.09, 9.0, 10.0, 720.0) is None                         # under both floors
    assert teleport(1 / 30, 5.0, 90.0, 0.0, 0.0) is None                           # 0 disables
    buf = PoseBuffer(max_gap_s=1.0, max_speed=10.0, max_rate_deg=720.0)
    buf.add(0, translation(0, 0, 0))
    assert buf.add(S // 30, translation(0.3, 0, 0)) is None
    assert buf.add(2 * S // 30, translation(0.8, 0, 0)) == (
        'odometry jumped 0.500 m in 0.033 s (15.0 m/s > odom_max_speed 10 m/s) at 0.067 s; pose buffer cleared')


def test_covariance_track_interpolates_and_reports_unfilled():
    from dpv_sensor.stream.pose_buffer import CovarianceTrack
    tr = CovarianceTrack()
    assert tr.at(5) is None
    tr.add(0, np.eye(6) * 1.0)
    tr.add(10, np.eye(6) * 3.0)
    np.testing.assert_allclose(tr.at(5), np.eye(6) * 2.0)
    np.testing.assert_allclose(tr.at(20), np.eye(6) * 3.0)
    tr.add(20, None)
    assert tr.at(15) is None
    tr.add(5, np.eye(6))          # time went backwards: the track starts again
    np.testing.assert_allclose(tr.at(100), np.eye(6))


def test_received_images_apply_the_stream_rules_before_the_pose_lookup():
    from dpv_sensor.stream.continuity import ImageVerdict, ReceivedImages
    buf = PoseBuffer(max_gap_s=1.0, max_speed=10.0, max_rate_deg=720.0)
    for t in range(5):
        buf.add(t * S, translation(0.01 * t, 0, 0))
    rules = ReceivedImages(buf)
    assert rules.image(2 * S, (64, 48)) == rules.image(3 * S, (64, 48)) == ImageVerdict()     # nothing to say
    assert rules.image(3 * S, (64, 48)).duplicate
    back = rules.image(1 * S, (64, 48))          # the odometry has not gone back: its samples are stale
    assert back.backwards == 'time went backwards (1.000 s after 3.000 s)' and back.poses_cleared
    assert back.previous_ns == 3 * S and back.size_change is None and len(buf) == 0
    resized = rules.image(2 * S, (32, 24))
    assert resized.size_change == 'image size changed from 64x48 to 32x24' and resized.previous_size == (64, 48)
    assert not rules.pose_teleported()
    buf.add(5 * S, translation(0.0, 0, 0))
    buf.add(6 * S, translation(50.0, 0, 0))      # 50 m in 1 s: a teleport the buffer counts
    assert buf.jumps == 1 and rules.pose_teleported() and not rules.pose_teleported()
