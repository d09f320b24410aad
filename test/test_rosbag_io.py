"""data/rosbag_io: sequences -> rosbag2 (MCAP and sqlite3) -> numpy, odometry rates/noise/dropouts; and
data/bag_export: a recorded bag of the node's outputs -> files."""
import math

import cv2
import numpy as np
import pytest

from dpv_sensor.ros import msgs as M
from dpv_sensor.data import rosbag_io as R
from dpv_sensor.data.bag_export import export_depth_bag
from dpv_sensor.stream.pose_buffer import NS, PoseBuffer, make_pose, pose7_to_matrix

W, H, N = 32, 24, 6
K = np.array([[30.0, 0.0, 15.5], [0.0, 30.0, 11.5], [0.0, 0.0, 1.0]])
T_BASE_CAM = [0.1, 0.0, 0.3, -0.5, 0.5, -0.5, 0.5]   # a typical base -> optical frame rotation


def trajectory(n=N):
    poses = []
    for i in range(n):
        a = math.radians(10.0 * i)
        poses.append(make_pose([0.05 * i, 0.01 * i * i, 0.0], [0.0, math.sin(a / 2), 0.0, math.cos(a / 2)]))
    return np.stack(poses)


def make_seq(n=N, rate=10.0):
    rng = np.random.default_rng(1)
    images = rng.integers(0, 256, size=(n, H, W, 3), dtype=np.uint8)
    return R.ArraySequence(images, trajectory(n), K, stamps=100.0 + np.arange(n) / rate)


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_sequence_round_trips_through_a_bag(tmp_path, storage):
    seq = make_seq()
    summary = R.write_sequence_bag(tmp_path / 'bag', seq, storage=storage, T_base_camera=T_BASE_CAM, progress=False)
    assert summary.frames == N and summary.odometry == N and summary.storage == storage
    topics = R.bag_topics(tmp_path / 'bag')
    assert topics == {'/image': ('sensor_msgs/msg/Image', N),
                      '/camera_info': ('sensor_msgs/msg/CameraInfo', N),
                      '/odom': ('nav_msgs/msg/Odometry', N)}
    expect_ns = [100 * NS + i * NS // 10 for i in range(N)]
    images = R.read_images(tmp_path / 'bag')
    assert [s.stamp_ns for s in images] == expect_ns == summary.image_stamps_ns
    assert [s.log_ns for s in images] == expect_ns
    assert {s.frame_id for s in images} == {'camera_optical_frame'}
    for i, s in enumerate(images):
        np.testing.assert_array_equal(s.data, seq.image(i))
        assert s.extra['encoding'] == 'rgb8'
    infos = R.read_camera_infos(tmp_path / 'bag')
    assert [s.stamp_ns for s in infos] == expect_ns
    np.testing.assert_allclose(infos[0].data, K)
    assert infos[0].extra['size'] == (W, H)
    odom = R.read_odometry(tmp_path / 'bag')
    assert {(s.frame_id, s.extra['child_frame_id']) for s in odom} == {('odom', 'base_link')}
    T_bc = pose7_to_matrix(T_BASE_CAM)
    for i, s in enumerate(odom):
        assert s.stamp_ns == expect_ns[i]
        np.testing.assert_allclose(s.data @ T_bc, seq.pose(i), atol=1e-12)
    qos = R.bag_qos(tmp_path / 'bag')['/image'][0]
    assert qos.reliability.name == 'RELIABLE'


def test_odometry_at_a_higher_rate_interpolates_back_to_the_camera_poses(tmp_path):
    seq = make_seq()
    summary = R.write_sequence_bag(tmp_path / 'bag', seq, odom_rate=50.0, T_base_camera=T_BASE_CAM, progress=False)
    odom = R.read_odometry(tmp_path / 'bag')
    assert summary.odometry == len(odom) == 5 * (N - 1) + 1
    stamps = [s.stamp_ns for s in odom]
    assert stamps == sorted(stamps) and stamps[0] == 100 * NS and stamps[-1] == 100 * NS + (N - 1) * NS // 10
    buf = PoseBuffer(max_gap_s=0.05, T_base_camera_44=pose7_to_matrix(T_BASE_CAM))
    for s in odom:
        buf.add(s.stamp_ns, s.data)
    for i, t in enumerate(summary.image_stamps_ns):
        np.testing.assert_allclose(buf.pose_at(t).T_world_cam_44, seq.pose(i), atol=1e-9)
    # in between, odometry lies on the SLERP/linear path between the frames (1/5 of the way to frame 1)
    T = odom[1].data @ pose7_to_matrix(T_BASE_CAM)
    np.testing.assert_allclose(T[:3, 3], 0.8 * seq.pose(0)[:3, 3] + 0.2 * seq.pose(1)[:3, 3], atol=1e-12)


def test_camera_rate_override_and_messages_in_time_order(tmp_path):
    seq = make_seq()
    R.write_sequence_bag(tmp_path / 'bag', seq, rate=5.0, start_ns=7 * NS, odom_rate=20.0, progress=False)
    msgs = list(R.read_messages(tmp_path / 'bag'))
    log = [m[2] for m in msgs]
    assert log == sorted(log)
    images = [m for m in msgs if m[0] == '/image']
    assert [M.stamp_to_ns(m[3].header.stamp) for m in images] == [7 * NS + i * NS // 5 for i in range(N)]
    # odometry at an image stamp comes before the camera_info, which comes before the image
    first = [m[0] for m in msgs if m[2] == 7 * NS]
    assert first == ['/odom', '/camera_info', '/image']


def test_odometry_noise_and_dropouts(tmp_path):
    seq = make_seq(n=41, rate=10.0)
    summary = R.write_sequence_bag(tmp_path / 'bag', seq, odom_rate=100.0, odom_noise=(0.01, 0.5),
                                   odom_dropout=0.3, seed=3, progress=False)
    odom = R.read_odometry(tmp_path / 'bag')
    total = 10 * 40 + 1
    assert summary.odometry == len(odom) and summary.odometry + summary.odometry_dropped == total
    assert 0.2 * total < summary.odometry_dropped < 0.4 * total
    assert odom[0].stamp_ns == 100 * NS and odom[-1].stamp_ns == 104 * NS    # the ends are never dropped
    clean = PoseBuffer(max_gap_s=1.0)
    for i in range(len(seq)):
        clean.add(int(round(seq.stamp(i) * NS)), seq.pose(i))
    err_t, err_r = [], []
    for s in odom:
        T = clean.pose_at(s.stamp_ns).T_world_cam_44
        err_t.append(s.data[:3, 3] - T[:3, 3])
        dR = T[:3, :3].T @ s.data[:3, :3]
        err_r.append(math.degrees(math.acos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))
    std = np.std(np.concatenate(err_t))
    assert 0.008 < std < 0.012
    # angle of a 3-D isotropic Gaussian rotation with sigma 0.5 deg per axis: mean 0.5*sqrt(8/pi) ~ 0.80 deg
    assert 0.65 < np.mean(err_r) < 0.95


def test_a_real_sequence_folder_can_be_written(tmp_path):
    from dpv_sensor.data.sequence import Sequence, write_sequence
    seq = make_seq()
    arrays = R.ArraySequence([seq.image(i) for i in range(N)], trajectory(), K, stamps=[seq.stamp(i) for i in range(N)],
                             depths=[np.ones((H, W), np.float32)] * N)
    write_sequence(tmp_path / 'seq', arrays, lossless=True)
    folder = Sequence(tmp_path / 'seq')
    R.write_sequence_bag(tmp_path / 'bag', folder, storage='sqlite3', progress=False, encoding='bgr8',
                         camera_frame='cam')
    images = R.read_images(tmp_path / 'bag')
    assert images[2].extra['encoding'] == 'bgr8' and images[2].frame_id == 'cam'
    np.testing.assert_array_equal(images[2].data, seq.image(2))


def test_generic_writer_takes_messages_and_raw_cdr_from_rclpy(tmp_path):
    from rclpy.serialization import serialize_message
    depth = np.array([[1.0, np.nan], [2.5, 3.0]], np.float32)
    ros_msg = M.depth_to_image(depth, 5 * NS + 1, 'cam')
    with R.BagWriter(tmp_path / 'bag') as bag:
        bag.write('/depth/image', R.IMAGE, bytes(serialize_message(ros_msg)), 5 * NS + 1)
        bag.write('/depth/image', R.IMAGE, M.depth_to_image(depth, 6 * NS, 'cam', types=R.ROSBAGS), 6 * NS)
    assert bag.counts == {'/depth/image': 2}
    out = R.read_depth_images(tmp_path / 'bag', '/depth/image')
    assert [s.stamp_ns for s in out] == [5 * NS + 1, 6 * NS]
    for s in out:
        np.testing.assert_array_equal(s.data, depth)
    with pytest.raises(R.BagError, match='exists already'):
        R.BagWriter(tmp_path / 'bag')
    with pytest.raises(R.BagError, match="no topic '/nope'"):
        R.read_images(tmp_path / 'bag', '/nope')
    with pytest.raises(R.BagError, match='carries sensor_msgs/msg/Image, expected sensor_msgs/msg/CameraInfo'):
        R.read_camera_infos(tmp_path / 'bag', '/depth/image')


def test_export_writes_depth_and_confidence_pngs(tmp_path):
    seq = make_seq(n=3)
    R.write_sequence_bag(tmp_path / 'in', seq, progress=False, T_base_camera=T_BASE_CAM)
    rng = np.random.default_rng(2)
    with R.BagWriter(tmp_path / 'out') as bag:
        for topic, msgtype, log_ns, msg in R.read_messages(tmp_path / 'in'):
            bag.write(topic, msgtype, msg, log_ns)
        depths, confs = [], []
        for i in range(3):
            t = int(round(seq.stamp(i) * NS))
            d = rng.uniform(0.5, 5.0, (H // 2, W // 2)).astype(np.float32)
            d[0, 0] = np.nan
            c = rng.uniform(0, 1, d.shape).astype(np.float32)
            depths.append(d)
            confs.append(c)
            bag.write('/ns/depth/image', R.IMAGE, M.depth_to_image(d, t, 'cam', types=R.ROSBAGS), t)
            bag.write('/ns/confidence/image', R.IMAGE, M.confidence_to_image(c, t, 'cam', types=R.ROSBAGS), t)
            Kd = M.scale_K(K, (W, H), (W // 2, H // 2))
            bag.write('/ns/depth/camera_info', R.CAMERA_INFO,
                      M.K_to_camera_info(Kd, W // 2, H // 2, t, 'cam', types=R.ROSBAGS), t)
    summary = export_depth_bag(tmp_path / 'out', tmp_path / 'export', T_base_camera=T_BASE_CAM, progress=False)
    assert summary['frames'] == 3 and summary['depth_topic'] == '/ns/depth/image'
    assert summary['without_confidence'] == summary['without_image'] == summary['without_pose'] == 0
    for i in range(3):
        mm = cv2.imread(str(tmp_path / 'export' / 'depth' / f'{i:06d}.png'), cv2.IMREAD_UNCHANGED)
        assert mm.dtype == np.uint16 and mm.shape == (H // 2, W // 2)
        expect = np.round(np.nan_to_num(depths[i], nan=0.0) * 1000)
        np.testing.assert_array_equal(mm, expect)
        cu = cv2.imread(str(tmp_path / 'export' / 'confidence' / f'{i:06d}.png'), cv2.IMREAD_UNCHANGED)
        np.testing.assert_allclose(cu / 65535.0, confs[i], atol=1e-5)
        rgb = cv2.imread(str(tmp_path / 'export' / 'images' / f'{i:06d}.png'))
        assert rgb.shape == (H // 2, W // 2, 3)
    np.testing.assert_allclose(np.loadtxt(tmp_path / 'export' / 'K.txt'), M.scale_K(K, (W, H), (W // 2, H // 2)))
    np.testing.assert_allclose(np.loadtxt(tmp_path / 'export' / 'stamps.txt'), [seq.stamp(i) for i in range(3)])
    poses = np.loadtxt(tmp_path / 'export' / 'poses.txt').reshape(-1, 4, 4)
    np.testing.assert_allclose(poses, trajectory(3), atol=1e-9)


def test_bag_command_line_write_and_export(tmp_path, capsys):
    from dpv_sensor.data.sequence import write_sequence
    from dpv_sensor.tools import bag as tool
    seq = make_seq()
    write_sequence(tmp_path / 'seq', R.ArraySequence([seq.image(i) for i in range(N)], trajectory(), K,
                                                     stamps=[seq.stamp(i) for i in range(N)]), lossless=True)
    code = tool.main(['bag', 'write', str(tmp_path / 'seq'), str(tmp_path / 'bag'), '--rate', '10', '--odom-rate',
                      '20', '--odom-noise', '0.01', '0.1', '--odom-dropout', '0.2', '--format', 'sqlite3',
                      '--camera-frame', 'cam', '--no-progress'])
    assert code == 0
    assert 'wrote' in capsys.readouterr().out
    assert list((tmp_path / 'bag').glob('*.db3'))
    topics = R.bag_topics(tmp_path / 'bag')
    assert topics['/image'] == ('sensor_msgs/msg/Image', N)
    assert 0 < topics['/odom'][1] <= 2 * (N - 1) + 1
    images = R.read_images(tmp_path / 'bag')
    assert [s.stamp_ns - images[0].stamp_ns for s in images] == [i * NS // 10 for i in range(N)]
    np.testing.assert_array_equal(images[3].data, seq.image(3))
    assert tool.main(['bag', 'write', str(tmp_path / 'seq'), str(tmp_path / 'bag'), '--no-progress']) == 1
    assert 'exists already' in capsys.readouterr().err

    with R.BagWriter(tmp_path / 'depth') as bag:
        for s in images:
            d = np.full((H, W), 1.5, np.float32)
            bag.write('/depth/image', R.IMAGE, M.depth_to_image(d, s.stamp_ns, 'cam', types=R.ROSBAGS), s.stamp_ns)
    assert tool.main(['bag', 'export', str(tmp_path / 'depth'), str(tmp_path / 'out'), '--no-progress']) == 0
    pngs = sorted((tmp_path / 'out' / 'depth').glob('*.png'))
    assert len(pngs) == N
    assert np.all(cv2.imread(str(pngs[0]), cv2.IMREAD_UNCHANGED) == 1500)
    assert (tmp_path / 'out' / 'stamps_ns.txt').read_text().split() == [str(s.stamp_ns) for s in images]


def test_export_finds_image_and_odometry_by_type(tmp_path):
    seq = make_seq(n=3)
    R.write_sequence_bag(tmp_path / 'in', seq, progress=False, image_topic='/a/rgb', camera_info_topic='/a/info',
                         odom_topic='/b/odometry')
    with R.BagWriter(tmp_path / 'out') as bag:
        for topic, msgtype, log_ns, msg in R.read_messages(tmp_path / 'in'):
            bag.write(topic, msgtype, msg, log_ns)
        for i in range(3):
            t = int(round(seq.stamp(i) * NS))
            bag.write('/depth/image', R.IMAGE, M.depth_to_image(np.ones((H, W), np.float32), t, 'cam',
                                                                 types=R.ROSBAGS), t)
    summary = export_depth_bag(tmp_path / 'out', tmp_path / 'export', progress=False)
    assert summary['image_topic'] == '/a/rgb' and summary['odom_topic'] == '/b/odometry'
    assert summary['chosen_by'] == {'image': 'the only sensor_msgs/msg/Image topic',
                                    'odom': 'the only nav_msgs/msg/Odometry topic'}
    assert len(list((tmp_path / 'export' / 'images').glob('*.png'))) == 3
    np.testing.assert_allclose(np.loadtxt(tmp_path / 'export' / 'poses.txt').reshape(-1, 4, 4), trajectory(3),
                               atol=1e-9)


def test_pose_variance_is_written_as_the_odometry_covariance(tmp_path):
    from dpv_sensor.core.pose_uncertainty import covariance_sigma
    seq = make_seq(n=5, rate=10.0)
    var = np.array([[0.0, 0.0], [1e-4, 4e-6], [4e-4, 1e-5], [9e-4, 2e-5], [16e-4, 3e-5]])
    R.write_sequence_bag(tmp_path / 'bag', seq, odom_rate=20.0, pose_variance=var, progress=False)
    covs = [np.asarray(m.pose.covariance).reshape(6, 6)
            for _t, _ty, _ns, m in R.read_messages(tmp_path / 'bag', [R.ODOM_TOPIC])]
    assert len(covs) == 9                                   # 20 Hz over 0.4 s
    assert np.all(np.diag(covs[0]) > 0)                     # the first pose's covariance reads as filled
    assert np.allclose(np.diag(covs[2])[:3], 1e-4) and np.allclose(np.diag(covs[2])[3:], 4e-6)   # frame 1
    assert np.allclose(np.diag(covs[3])[:3], 2.5e-4)        # halfway between frames 1 and 2: linear in time
    assert np.count_nonzero(covs[4] - np.diag(np.diag(covs[4]))) == 0   # diagonal
    sigma = covariance_sigma(covs[2], covs[6])              # frames 1 -> 3: the growth between them
    assert sigma.trans_m == pytest.approx(math.sqrt(8e-4)) and sigma.rot_rad == pytest.approx(math.sqrt(1.6e-5))
    with pytest.raises(R.BagError, match='one row'):
        R.write_sequence_bag(tmp_path / 'bad', seq, pose_variance=var[:3], progress=False)
    with pytest.raises(R.BagError, match='non-negative'):
        R.write_sequence_bag(tmp_path / 'bad2', seq, pose_variance=-var, progress=False)


def test_twist_variance_is_written_as_the_odometry_twist_covariance(tmp_path):
    seq = make_seq(n=5, rate=10.0)
    twist = np.array([[1e-4, 4e-6], [1e-4, 4e-6], [3e-4, 8e-6], [2e-4, 1e-5], [5e-4, 3e-5]])
    R.write_sequence_bag(tmp_path / 'bag', seq, odom_rate=20.0, pose_variance=np.full((5, 2), 1e-3),
                         twist_variance=twist, progress=False)
    msgs = [m for _t, _ty, _ns, m in R.read_messages(tmp_path / 'bag', [R.ODOM_TOPIC])]
    poses = [np.asarray(m.pose.covariance).reshape(6, 6) for m in msgs]
    twists = [np.asarray(m.twist.covariance).reshape(6, 6) for m in msgs]
    assert all(np.array_equal(p, poses[0]) for p in poses)                # the pose covariance stays constant
    np.testing.assert_allclose(np.diag(twists[4]), [3e-4] * 3 + [8e-6] * 3)      # frame 2
    np.testing.assert_allclose(np.diag(twists[5]), [2.5e-4] * 3 + [9e-6] * 3)    # halfway to frame 3: linear
    assert np.count_nonzero(twists[5] - np.diag(np.diag(twists[5]))) == 0
    R.write_sequence_bag(tmp_path / 'plain', seq, odom_rate=20.0, progress=False)
    assert not any(np.any(m.twist.covariance) for _t, _ty, _ns, m in R.read_messages(tmp_path / 'plain',
                                                                                         [R.ODOM_TOPIC]))
    with pytest.raises(R.BagError, match='twist_variance must be finite'):
        R.write_sequence_bag(tmp_path / 'bad', seq, twist_variance=-twist, progress=False)


def test_the_mount_on_tf_static_as_a_two_link_chain(tmp_path):
    """bag write --tf-static: odometry of base_link and the mount on /tf_static, latched, written first; the chain
    base_link -> camera_link -> camera frame composes to T_base_camera, so odometry @ chain = the camera poses."""
    from dpv_sensor.ros.pose_msgs import transform_to_matrix
    from dpv_sensor.stream.transform_tree import TransformTree
    seq = make_seq()
    R.write_sequence_bag(tmp_path / 'bag', seq, T_base_camera=T_BASE_CAM, tf_static=True, camera_link='camera_link',
                         progress=False)
    assert R.bag_topics(tmp_path / 'bag')['/tf_static'] == ('tf2_msgs/msg/TFMessage', 1)
    qos = R.bag_qos(tmp_path / 'bag')['/tf_static'][0]
    assert (qos.reliability.name, qos.durability.name) == ('RELIABLE', 'TRANSIENT_LOCAL')
    first = next(R.read_messages(tmp_path / 'bag'))
    assert first[0] == '/tf_static' and first[2] == 100 * NS
    tree = TransformTree()
    links = [(tf.header.frame_id, tf.child_frame_id) for tf in first[3].transforms]
    assert links == [('base_link', 'camera_link'), ('camera_link', 'camera_optical_frame')]
    for tf in first[3].transforms:
        tree.set(tf.header.frame_id, tf.child_frame_id, transform_to_matrix(tf.transform), static=True)
    T_bc = tree.lookup('base_link', 'camera_optical_frame').T_target_source_44
    np.testing.assert_allclose(T_bc, pose7_to_matrix(T_BASE_CAM), atol=1e-12)
    for i, s in enumerate(R.read_odometry(tmp_path / 'bag')):
        np.testing.assert_allclose(s.data @ T_bc, seq.pose(i), atol=1e-12)
    R.write_sequence_bag(tmp_path / 'one', seq, T_base_camera=T_BASE_CAM, tf_static=True, progress=False)
    one = next(R.read_messages(tmp_path / 'one', ['/tf_static']))[3].transforms
    assert [(tf.header.frame_id, tf.child_frame_id) for tf in one] == [('base_link', 'camera_optical_frame')]


def test_the_topics_of_a_bag_rewritten_at_the_same_path_are_read_again(tmp_path):
    """bag_topics reads a bag's metadata once per version of it: a bag written again at the same path (another
    recording, other topics and counts) gives its own topics, a missing bag the usual error."""
    import shutil
    seq = make_seq(4)
    R.write_sequence_bag(tmp_path / 'bag', seq, progress=False)
    first = R.bag_topics(tmp_path / 'bag')
    assert first[R.ODOM_TOPIC] == (R.ODOMETRY, 4) and first[R.IMAGE_TOPIC] == (R.IMAGE, 4)
    assert R.bag_topics(str(tmp_path / 'bag')) == first                 # the same bag, by another spelling
    shutil.rmtree(tmp_path / 'bag')
    R.write_sequence_bag(tmp_path / 'bag', make_seq(3), progress=False, with_odometry=False)
    second = R.bag_topics(tmp_path / 'bag')
    assert R.ODOM_TOPIC not in second and second[R.IMAGE_TOPIC] == (R.IMAGE, 3), second
    shutil.rmtree(tmp_path / 'bag')
    with pytest.raises(R.BagError, match='no such bag'):
        R.bag_topics(tmp_path / 'bag')
