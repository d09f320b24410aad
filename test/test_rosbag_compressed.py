"""Bags with image_transport's compressed colour images (sensor_msgs/CompressedImage, JPEG / PNG), as robots record
cameras: `bag write --compressed` writes them, the readers decode them, and the tools find them by type (a raw
Image topic preferred when a bag holds both), so that `make demo BAG=`, `bag export`, `evaluate bag` and `fuse bag`
read such bags."""
import numpy as np
import pytest

from dpv_sensor.data import rosbag_io as R
from dpv_sensor.data.bag_export import export_depth_bag
from dpv_sensor.data.topic_detection import (detect_image_topic, detect_input_topics, image_topic_line,
                                             image_transport_of)
from dpv_sensor.stream.pose_buffer import NS

W, H, N = 64, 48, 5
K = np.array([[60.0, 0.0, 31.5], [0.0, 60.0, 23.5], [0.0, 0.0, 1.0]])


def make_seq(n=N, rate=10.0):
    y, x = np.mgrid[0:H, 0:W]
    images = [np.stack([(x * 4 + 10 * i) % 256, y * 5, (x + y) * 2], -1).astype(np.uint8) for i in range(n)]
    poses = np.stack([np.eye(4) for _ in range(n)])
    poses[:, 0, 3] = 0.02 * np.arange(n)
    depths = [np.full((H, W), 2.0, np.float32) for _ in range(n)]
    return R.ArraySequence(images, poses, K, stamps=100.0 + np.arange(n) / rate, depths=depths)


@pytest.mark.parametrize('codec,fmt,max_mean_err', [('jpeg', 'rgb8; jpeg compressed bgr8', 3.0),
                                                    ('png', 'rgb8; png compressed bgr8', 0.0)])
def test_compressed_bag_round_trip(tmp_path, codec, fmt, max_mean_err):
    seq = make_seq()
    summary = R.write_sequence_bag(tmp_path / 'bag', seq, compressed=codec, progress=False)
    assert summary.image_topic == '/image/compressed' and summary.image_format == fmt
    topics = R.bag_topics(tmp_path / 'bag')
    assert topics == {'/image/compressed': (R.COMPRESSED_IMAGE, N), '/camera_info': (R.CAMERA_INFO, N),
                      '/odom': (R.ODOMETRY, N)}
    images = R.read_images(tmp_path / 'bag', '/image/compressed')
    assert [s.stamp_ns for s in images] == [100 * NS + i * NS // 10 for i in range(N)]
    assert {s.frame_id for s in images} == {'camera_optical_frame'} and images[0].extra['format'] == fmt
    for i, s in enumerate(images):
        err = np.abs(s.data.astype(int) - seq.image(i).astype(int)).mean()
        assert s.data.shape == (H, W, 3) and err <= max_mean_err, (i, err)


def test_jpeg_quality_changes_the_payload(tmp_path):
    seq = make_seq(n=2)
    sizes = {}
    for q in (30, 95):
        R.write_sequence_bag(tmp_path / f'q{q}', seq, compressed='jpeg', jpeg_quality=q, progress=False)
        sizes[q] = sum(len(m.data) for _t, _ty, _l, m in R.read_messages(tmp_path / f'q{q}', ['/image/compressed']))
    assert sizes[30] < sizes[95]
    with pytest.raises(R.BagError, match='jpeg_quality'):
        R.write_sequence_bag(tmp_path / 'bad', seq, compressed='jpeg', jpeg_quality=0, progress=False)
    with pytest.raises(R.BagError, match='compressed must be one of jpeg, png'):
        R.write_sequence_bag(tmp_path / 'bad', seq, compressed='webp', progress=False)


def test_bag_write_compressed_on_the_command_line(tmp_path, capsys):
    from dpv_sensor.data.sequence import write_sequence
    from dpv_sensor.tools import bag as tool
    seq = make_seq()
    write_sequence(tmp_path / 'seq', seq, lossless=True)
    assert tool.main(['bag', 'write', str(tmp_path / 'seq'), str(tmp_path / 'jpeg'), '--compressed', '--rate', '30',
                      '--no-progress']) == 0
    out = capsys.readouterr().out
    assert "CompressedImage 'rgb8; jpeg compressed bgr8' on /image/compressed" in out, out
    assert R.bag_topics(tmp_path / 'jpeg')['/image/compressed'] == (R.COMPRESSED_IMAGE, N)
    assert tool.main(['bag', 'write', str(tmp_path / 'seq'), str(tmp_path / 'png'), '--compressed', 'png',
                      '--image-topic', '/cam/color/image_raw/compressed', '--camera-info-topic',
                      '/cam/color/camera_info', '--frames', '3', '--no-progress']) == 0
    topics = R.bag_topics(tmp_path / 'png')
    assert topics['/cam/color/image_raw/compressed'] == (R.COMPRESSED_IMAGE, 3)
    np.testing.assert_array_equal(R.read_images(tmp_path / 'png', '/cam/color/image_raw/compressed')[2].data,
                                  seq.image(2))
    assert tool.main(['bag', 'write', str(tmp_path / 'seq'), str(tmp_path / 'raw'), '--no-progress']) == 0
    assert R.bag_topics(tmp_path / 'raw')['/image'] == (R.IMAGE, N)


# ---- which topic is which ----------------------------------------------------------------------------------------
ROBOT = {'/cam/color/image_raw/compressed': (R.COMPRESSED_IMAGE, 30), '/cam/color/camera_info': (R.CAMERA_INFO, 30),
         '/cam/depth/camera_info': (R.CAMERA_INFO, 30),
         '/cam/depth/image_raw/compressedDepth': (R.COMPRESSED_IMAGE, 30), '/odom': (R.ODOMETRY, 300)}


def test_a_compressed_camera_topic_is_found_by_type_with_its_camera_info():
    chosen, how = detect_input_topics(ROBOT)
    assert chosen == {'image': '/cam/color/image_raw/compressed', 'camera_info': '/cam/color/camera_info',
                      'odom': '/odom'}
    assert how['image'] == 'the only sensor_msgs/msg/CompressedImage topic'       # compressedDepth left out
    assert how['camera_info'] == 'the only sensor_msgs/msg/CameraInfo topic next to /cam/color/image_raw'
    assert image_transport_of(ROBOT, chosen['image']) == 'compressed'


def test_a_raw_topic_is_preferred_to_compressed_ones_unless_named():
    topics = dict(ROBOT, **{'/cam/color/image_raw': (R.IMAGE, 30)})
    chosen, how = detect_input_topics(topics)
    assert chosen['image'] == '/cam/color/image_raw' and image_transport_of(topics, chosen['image']) == 'raw'
    assert 'preferred to 1 sensor_msgs/msg/CompressedImage topic(s)' in how['image']
    chosen, how = detect_input_topics(topics, image='/cam/color/image_raw/compressed')
    assert chosen['image'] == '/cam/color/image_raw/compressed' and how['image'] == 'named'


def test_several_compressed_topics_need_a_name_and_no_image_is_a_clear_error():
    topics = dict(ROBOT, **{'/cam2/image_raw/compressed': (R.COMPRESSED_IMAGE, 30)})
    with pytest.raises(R.BagError, match='2 sensor_msgs/msg/CompressedImage topics could be the image'):
        detect_input_topics(topics)
    no_image = {'/cam/depth/image_raw/compressedDepth': (R.COMPRESSED_IMAGE, 3), '/odom': (R.ODOMETRY, 3)}
    with pytest.raises(R.BagError, match='no sensor_msgs/msg/Image or sensor_msgs/msg/CompressedImage topic'):
        detect_input_topics(no_image)
    assert detect_image_topic(no_image, required=False) == (None, 'absent')


def test_the_image_topic_line_names_type_codec_and_transport(tmp_path):
    R.write_sequence_bag(tmp_path / 'bag', make_seq(n=2), compressed='jpeg', progress=False)
    topics = R.bag_topics(tmp_path / 'bag')
    assert image_topic_line(tmp_path / 'bag', topics, '/image/compressed') == (
        "image topic: /image/compressed (sensor_msgs/CompressedImage, JPEG 'rgb8; jpeg compressed bgr8') -> node "
        'image_transport=compressed')


def test_export_and_evaluate_take_a_compressed_camera_topic(tmp_path):
    from dpv_sensor.data.sequence import write_sequence
    from dpv_sensor.evaluation.recorded import records_from_bag
    from dpv_sensor.ros import msgs as M
    seq = make_seq()
    write_sequence(tmp_path / 'gt', seq, lossless=True)
    R.write_sequence_bag(tmp_path / 'in', seq, compressed='jpeg', start_ns=5 * NS, progress=False)
    with R.BagWriter(tmp_path / 'out') as bag:
        for topic, msgtype, log_ns, msg in R.read_messages(tmp_path / 'in'):
            bag.write(topic, msgtype, msg, log_ns)
        for i in range(1, N):
            t = 5 * NS + i * NS // 10
            bag.write('/depth/image', R.IMAGE, M.depth_to_image(np.full((H, W), 2.0, np.float32), t, 'cam',
                                                                 types=R.ROSBAGS), t)
    summary = export_depth_bag(tmp_path / 'out', tmp_path / 'export', progress=False)
    assert summary['image_topic'] == '/image/compressed' and summary['without_image'] == 0
    assert len(list((tmp_path / 'export' / 'images').glob('*.png'))) == N - 1
    records, info = records_from_bag(tmp_path / 'out', tmp_path / 'gt')
    assert info['image_topic'] == '/image/compressed' and abs(info['stamp_offset'] - (5.0 - 100.0)) < 1e-6
    assert info['matched'] == N - 1, info
