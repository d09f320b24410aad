"""Reading a user's recording for the adaptation (dpv_sensor.data.recording): a rosbag2 (camera image raw or
compressed, camera_info, odometry, the camera mount on /tf_static) or a sequence folder, never its depth."""
import numpy as np
import pytest

from dpv_sensor.data import rosbag_io as R
from dpv_sensor.data.recording import load_recording
from dpv_sensor.data.sequence import SequenceFormatError, write_sequence
from dpv_sensor.data.synthetic import render_sequence
from dpv_sensor.stream.pose_buffer import pose7_to_matrix

# the camera 12 cm ahead of and 30 cm above base_link, looking forward (optical frame: z forward, x right, y down)
MOUNT = [0.12, 0.0, 0.30, -0.5, 0.5, -0.5, 0.5]


@pytest.fixture(scope='module')
def rendered():
    return render_sequence(5, 24, width=96, height=72)


def _rotation_deg(A, B):
    c = (np.trace(A[:3, :3].T @ B[:3, :3]) - 1) / 2
    return np.degrees(np.arccos(np.clip(c, -1, 1)))


@pytest.mark.parametrize('compressed', [None, 'png'])
def test_a_bag_gives_the_camera_poses_through_the_mount_on_tf_static(rendered, tmp_path, compressed):
    bag = tmp_path / 'run.mcap'
    # odometry at 45 Hz (not at the image stamps): the poses are interpolated, as the node pairs them
    R.write_sequence_bag(bag, rendered, odom_rate=45.0, T_base_camera=MOUNT, tf_static=True, camera_link='camera_link',
                         compressed=compressed, progress=False, start_ns=1_700_000_000 * R.NS)
    rec = load_recording(bag, size=(48, 36))
    seq = rec.sequence
    assert rec.source['kind'] == 'bag' and rec.source['native_size'] == [96, 72] and len(seq) == len(rendered)
    assert rec.source['camera_mount'].startswith('/tf_static base_link -> ')
    assert not seq.has_depth and rec.source['depth_read'] is False
    with pytest.raises(SequenceFormatError):
        seq.depth(0)
    assert seq.size == (48, 36)
    # K scaled to the size read (fx' = fx / 2, cx' = (cx + 0.5) / 2 - 0.5)
    K = rendered.K
    np.testing.assert_allclose(seq.K[0, 0], K[0, 0] / 2, rtol=1e-9)
    np.testing.assert_allclose(seq.K[1, 2], (K[1, 2] + 0.5) / 2 - 0.5, rtol=1e-9)
    for i in (0, 7, len(seq) - 1):
        T, T_gt = seq.pose(i), rendered.pose(i)
        assert np.linalg.norm(T[:3, 3] - T_gt[:3, 3]) < 2e-3 and _rotation_deg(T, T_gt) < 0.2
    # the image itself: the rendered frame scaled down (PNG is lossless; the raw topic is exact)
    import cv2
    small = cv2.resize(rendered.image(7), (48, 36), interpolation=cv2.INTER_AREA)
    assert np.abs(seq.image(7).astype(int) - small.astype(int)).max() <= 1


def test_a_bag_without_the_mount_uses_the_one_given_or_the_identity(rendered, tmp_path):
    bag = tmp_path / 'run.mcap'
    R.write_sequence_bag(bag, rendered, T_base_camera=MOUNT, progress=False)      # no /tf_static
    given = load_recording(bag, T_base_camera=MOUNT)
    assert given.source['camera_mount'] == 'given'
    assert np.linalg.norm(given.sequence.pose(5)[:3, 3] - rendered.pose(5)[:3, 3]) < 1e-6
    bare = load_recording(bag)
    assert bare.source['camera_mount'] == 'identity'
    # the identity leaves the base pose: off by the mount (0.32 m away, a quarter turn about two axes)
    T_world_base = rendered.pose(5) @ np.linalg.inv(pose7_to_matrix(np.asarray(MOUNT)))
    np.testing.assert_allclose(bare.sequence.pose(5), T_world_base, atol=1e-6)


def test_a_folder_is_read_without_ever_looking_at_depth(rendered, tmp_path):
    folder = write_sequence(tmp_path / 'seq', rendered, lossless=True)
    # a depth folder that could not be read: the recording never opens it
    for p in (folder / 'depth').iterdir():
        p.write_bytes(b'not a png')
    (folder / 'depth' / '000003.png').unlink()
    rec = load_recording(folder)
    assert rec.source['kind'] == 'folder' and len(rec.sequence) == len(rendered) and not rec.sequence.has_depth
    np.testing.assert_array_equal(rec.sequence.image(3), rendered.image(3))
    np.testing.assert_allclose(rec.sequence.poses, rendered.poses)


def test_neither_a_folder_nor_a_bag(tmp_path):
    with pytest.raises(FileNotFoundError, match='no such sequence folder or bag'):
        load_recording(tmp_path / 'missing')
    (tmp_path / 'empty').mkdir()
    with pytest.raises(SequenceFormatError, match='poses.txt is missing'):
        load_recording(tmp_path / 'empty')


def test_a_bag_depth_topic_is_read_only_when_asked_and_paired_by_stamp(rendered, tmp_path):
    bag = tmp_path / 'run.mcap'
    R.write_sequence_bag(bag, rendered, T_base_camera=MOUNT, tf_static=True, depth_topic='/camera/aligned_depth/image',
                         progress=False, start_ns=1_700_000_000 * R.NS)
    # the depth topic is one more sensor_msgs/Image topic: named, it is never taken for the colour image
    rec = load_recording(bag, size=(48, 36), depth_topic='/camera/aligned_depth/image')
    seq = rec.sequence
    assert seq.has_depth and rec.source['depth_read'] is True and len(seq) == len(rendered)
    assert rec.source['depth_topic'] == '/camera/aligned_depth/image' and rec.source['depth_offset_ms_max'] == 0
    from dpv_sensor.data.sequence import resize_nearest
    want = resize_nearest(np.round(rendered.depth(7) * 1000) / 1000, 48, 36)      # 16UC1: millimetres
    np.testing.assert_allclose(seq.depth(7), want, atol=1e-6)
    assert not load_recording(bag, image_topic='/image').sequence.has_depth       # not asked: never read


def test_depth_pairs_take_the_nearest_within_20_ms_and_refuse_another_size(tmp_path):
    from dpv_sensor.data import recording
    from dpv_sensor.ros import msgs as M
    ms = R.NS // 1000
    with R.BagWriter(tmp_path / 'bag') as bag:
        for t_ms, value, size in ((0, 1.0, (4, 3)), (33, 2.0, (4, 3)), (91, 3.0, (4, 3)), (200, 4.0, (8, 6))):
            d = np.full((size[1], size[0]), value, np.float32)
            bag.write('/depth', R.IMAGE, M.depth_to_image(d, t_ms * ms, 'cam', types=R.ROSBAGS), t_ms * ms)
    pairs = recording._DepthPairs(tmp_path / 'bag', '/depth')
    assert pairs.at(10 * ms, (4, 3))[0, 0] == 1.0            # 10 ms from 0, 23 ms from 33
    assert pairs.at(50 * ms, (4, 3))[0, 0] == 2.0            # 17 ms: an unsynchronised 30 Hz depth camera
    assert pairs.at(62 * ms, (4, 3)) is None                 # 29 ms from both: no pair
    assert pairs.worst_offset_s == pytest.approx(0.017)
    with pytest.raises(R.BagError, match='depth images are 8x6 but the colour images 4x3: record the depth '
                                         'registered'):
        pairs.at(200 * ms, (4, 3))
    with pytest.raises(SequenceFormatError, match='a depth topic is read from a bag'):
        load_recording(tmp_path, depth_topic='/depth')
