"""The node's pose output over real DDS: a rendered sequence replayed as a rosbag2 into two node processes.

Node /ref runs with odometry and `pose_refinement: window` (odometry sigmas set through the parameters); node /vo runs
without odometry (`odometry: none`, visual odometry + the same window). Checked:
- both publish `pose` (geometry_msgs/PoseStamped) with the exact stamp of every depth image they publish, in the
  odometry frame of the bag (/ref) or 'odom' (/vo);
- /ref's refined poses stay on the (exact) odometry poses of the rendered camera, and it reports tracking ok;
- /vo's poses rotate like the rendered camera (monocular: its translation scale is arbitrary, its rotation is not);
- /ref (publish_tf) puts each refined pose on /tf as map -> cam_optical_refined with its stamp; /vo (publish_tf
  off, the default) puts nothing there.
"""
import threading

import numpy as np
import pytest

from ros_helpers import assert_clean_exits, start_node, stop_all, wait_for
from test_node_integration import COMMON, FRAMES, H, START_NS, T_BASE_CAMERA, W, ros_args
from dpv_sensor.ros import msgs as M
from dpv_sensor.data import rosbag_io as R
from dpv_sensor.core.photometric import pose_error
from dpv_sensor.stream.pose_buffer import make_pose
from dpv_sensor.client.ros_io import BagPlayer, OutputCollector


@pytest.fixture(scope='module')
def scene(tmp_path_factory):
    from dpv_sensor.data.synthetic import render_sequence
    seq = render_sequence(3, FRAMES, width=W, height=H)
    bag = tmp_path_factory.mktemp('bags') / 'synthetic'
    summary = R.write_sequence_bag(bag, seq, odom_rate=60.0, start_ns=START_NS, T_base_camera=T_BASE_CAMERA,
                                   camera_frame='cam_optical', odom_frame='map', progress=False)
    return seq, bag, summary


class PoseCollector:
    def __init__(self, node, topic):
        from geometry_msgs.msg import PoseStamped
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        self.by_stamp = {}
        self.frames = set()
        self.sub = node.create_subscription(PoseStamped, topic, self._on,
                                            QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE))

    def _on(self, msg):
        p, q = msg.pose.position, msg.pose.orientation
        self.by_stamp[M.stamp_to_ns(msg.header.stamp)] = make_pose([p.x, p.y, p.z], [q.x, q.y, q.z, q.w])
        self.frames.add(msg.header.frame_id)


class TfCollector:
    """Transforms on /tf by (parent, child, stamp)."""

    def __init__(self, node):
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from tf2_msgs.msg import TFMessage
        self.by_key = {}
        self.sub = node.create_subscription(TFMessage, '/tf', self._on,
                                            QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))

    def _on(self, msg):
        for tf in msg.transforms:
            t, q = tf.transform.translation, tf.transform.rotation
            key = (tf.header.frame_id, tf.child_frame_id, M.stamp_to_ns(tf.header.stamp))
            self.by_key[key] = make_pose([t.x, t.y, t.z], [q.x, q.y, q.z, q.w])

    def stamps(self, parent, child):
        return {s for p, c, s in self.by_key if (p, c) == (parent, child)}


def test_refined_and_visual_odometry_poses_are_published_with_every_depth_image(scene, observer):
    seq, bag, summary = scene
    node, executor = observer
    spin = lambda t: executor.spin_once(timeout_sec=t)  # noqa: E731
    ref = OutputCollector(node, namespace='/ref', diagnostics_name='ref/dpv_sensor: depth camera')
    vo = OutputCollector(node, namespace='/vo', diagnostics_name='vo/dpv_sensor: depth camera')
    ref_poses, vo_poses = PoseCollector(node, '/ref/pose'), PoseCollector(node, '/vo/pose')
    tf = TfCollector(node)
    env = {'OMP_NUM_THREADS': '1'}
    proc_ref = start_node(ros_args({**COMMON, 'T_base_camera': T_BASE_CAMERA, 'pose_refinement': 'window',
                                    'publish_tf': True, 'odom_sigma_rot_deg': 0.2, 'odom_sigma_trans_rel': 0.02},
                                   ['-r', '__ns:=/ref']), env=env)
    proc_vo = start_node(ros_args({**COMMON, 'odometry': 'none'}, ['-r', '__ns:=/vo']), env=env)
    player = BagPlayer(node, bag, rate=0.2)
    played = {}
    try:
        ready = wait_for(lambda: all(c.diagnostics.get('measurement_model') == 'classical'
                                     and c.diag_int('publishers.image') == 1 for c in (ref, vo))
                         and ref.diag_int('publishers.odom') == 1
                         and ref_poses.sub.get_publisher_count() == 1 and vo_poses.sub.get_publisher_count() == 1,
                         timeout=60.0, spin=spin)
        assert proc_ref.poll() is None and proc_vo.poll() is None, 'a node exited early'
        assert ready, f'the nodes never got ready: ref {ref.diagnostics} vo {vo.diagnostics}'
        images = [t for t in player.topics if t != '/odom']
        assert not player.wait_for_subscribers(images, min_count=2, timeout=10.0, spin=spin)
        assert not player.wait_for_subscribers(['/odom'], min_count=1, timeout=10.0, spin=spin)
        thread = threading.Thread(target=lambda: played.update(stats=player.play()), daemon=True)
        thread.start()
        done = wait_for(lambda: not thread.is_alive()
                        and all(c.diag_int('frames_received') == FRAMES
                                and c.diag_int('frames_processed') + c.diag_int('dropped_total') == FRAMES
                                and c.diag_int('outputs_published', -1) == len(c.complete()) for c in (ref, vo))
                        and set(ref_poses.by_stamp) >= {r.stamp_ns for r in ref.complete()}
                        and set(vo_poses.by_stamp) >= {r.stamp_ns for r in vo.complete()}
                        and tf.stamps('map', 'cam_optical_refined') >= set(ref_poses.by_stamp),
                        timeout=90.0, spin=spin)
        assert done, (f'replay did not finish: ref {ref.diagnostics} poses {len(ref_poses.by_stamp)}; '
                      f'vo {vo.diagnostics} poses {len(vo_poses.by_stamp)}')
    finally:
        exits = stop_all(proc_ref, proc_vo)
        player.stop()
    assert_clean_exits(exits)
    idx = {t: i for i, t in enumerate(summary.image_stamps_ns)}

    # /ref: a refined pose for every depth image, in the bag's odometry frame, on the exact odometry
    outs = ref.complete()
    assert len(outs) >= 4, ref.diagnostics
    assert set(ref_poses.by_stamp) == {r.stamp_ns for r in outs} and ref_poses.frames == {'map'}
    assert ref.diagnostics.get('pose_refinement_tracking') == 'ok', ref.diagnostics
    for s, T in ref_poses.by_stamp.items():
        t_err, r_err = pose_error(seq.pose(idx[s]), T)
        assert t_err < 0.03 and r_err < 1.0, (idx[s], t_err, r_err)

    # /ref's refined poses on /tf as a frame of their own; nothing from /vo (publish_tf off)
    assert {(p, c) for p, c, _ in tf.by_key} == {('map', 'cam_optical_refined')}
    assert tf.stamps('map', 'cam_optical_refined') == set(ref_poses.by_stamp)
    for s, T in ref_poses.by_stamp.items():
        np.testing.assert_allclose(tf.by_key[('map', 'cam_optical_refined', s)], T, atol=1e-9)

    # /vo: a pose for every depth image, frame 'odom', rotating like the camera
    outs = vo.complete()
    assert len(outs) >= 4, vo.diagnostics
    assert set(vo_poses.by_stamp) == {r.stamp_ns for r in outs} and vo_poses.frames == {'odom'}
    stamps = sorted(vo_poses.by_stamp)
    rot_err, rot_gt = [], []
    for a, b in zip(stamps[:-1], stamps[1:]):
        rel_vo = np.linalg.inv(vo_poses.by_stamp[a]) @ vo_poses.by_stamp[b]
        rel_gt = np.linalg.inv(seq.pose(idx[a])) @ seq.pose(idx[b])
        rot_err.append(pose_error(rel_gt, rel_vo)[1])
        rot_gt.append(pose_error(rel_gt, np.eye(4))[1])
    print(f'/vo keyframes {len(stamps)}: relative rotation error mean {np.mean(rot_err):.3f} deg, '
          f'max {np.max(rot_err):.3f} deg; the camera turned {np.mean(rot_gt):.3f} deg per keyframe')
    assert np.mean(rot_err) < 0.75 and np.max(rot_err) < 2.0
    assert np.mean(rot_err) < 0.5 * np.mean(rot_gt), 'the VO rotation is no better than assuming none'
