"""dpv_sensor.msgs: ROS messages <-> numpy, exact stamps and frame ids, and the specific errors for bad input."""
import math

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from sensor_msgs.msg import Image
from std_msgs.msg import Header

from dpv_sensor import msgs as M
from dpv_sensor.pose_buffer import make_pose

RNG = np.random.default_rng(7)
RGB = RNG.integers(0, 256, size=(5, 7, 3), dtype=np.uint8)


def header(sec=1_700_000_000, nanosec=123_456_789, frame_id='camera_optical_frame'):
    return Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=frame_id)


def raw_image(pixels_hwc: np.ndarray, encoding: str, pad: int = 0, bigendian: int = 0) -> Image:
    """An Image whose rows carry `pad` junk bytes after the pixels (step > width * bytes per pixel)."""
    h, w = pixels_hwc.shape[:2]
    rows = pixels_hwc.reshape(h, -1).view(np.uint8)
    junk = np.full((h, pad), 0xAB, np.uint8)
    data = np.concatenate([rows, junk], axis=1)
    return Image(header=header(), height=h, width=w, encoding=encoding, is_bigendian=bigendian,
                 step=data.shape[1], data=data.tobytes())


# ---------------------------------------------------------------- colour input
@pytest.mark.parametrize('pad', [0, 3])
def test_colour_encodings_decode_to_rgb_with_step_padding(pad):
    alpha = np.full(RGB.shape[:2] + (1,), 9, np.uint8)
    cases = {
        'rgb8': RGB,
        'bgr8': RGB[:, :, ::-1],
        'rgba8': np.concatenate([RGB, alpha], 2),
        'bgra8': np.concatenate([RGB[:, :, ::-1], alpha], 2),
    }
    for enc, px in cases.items():
        out = M.image_to_rgb(raw_image(np.ascontiguousarray(px), enc, pad=pad))
        assert out.dtype == np.uint8 and out.shape == RGB.shape, enc
        np.testing.assert_array_equal(out, RGB, err_msg=enc)
    grey = RGB[:, :, 1:2].copy()
    out = M.image_to_rgb(raw_image(grey, 'mono8', pad=pad))
    np.testing.assert_array_equal(out, np.repeat(grey, 3, axis=2))


def test_is_bigendian_does_not_matter_for_8_bit_colour():
    np.testing.assert_array_equal(M.image_to_rgb(raw_image(RGB, 'rgb8', bigendian=1)), RGB)


def test_rgb_to_image_round_trips_every_encoding_and_keeps_the_header():
    h = header(sec=42, nanosec=999_999_999, frame_id='cam')
    for enc in ('rgb8', 'bgr8', 'rgba8', 'bgra8'):
        msg = M.rgb_to_image(RGB, h, encoding=enc)
        assert msg.encoding == enc and msg.step == RGB.shape[1] * (4 if 'a' in enc else 3)
        assert (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id) == (42, 999_999_999, 'cam')
        np.testing.assert_array_equal(M.image_to_rgb(msg), RGB)


@pytest.mark.parametrize('encoding,fragment', [
    ('16UC1', "'16UC1' (a 16-bit depth/mono image)"),
    ('32FC1', "'32FC1' (a float depth image)"),
    ('bayer_rggb8', 'debayer'),
    ('yuv422', 'YUV'),
    ('foo', "unsupported image encoding 'foo'"),
])
def test_non_colour_encodings_raise_unsupported_encoding(encoding, fragment):
    msg = raw_image(np.zeros((4, 4, 2), np.uint8), encoding)
    with pytest.raises(M.UnsupportedEncoding) as err:
        M.image_to_rgb(msg)
    assert fragment in str(err.value)
    assert 'rgb8, bgr8, rgba8, bgra8, mono8' in str(err.value)


def test_inconsistent_images_raise_bad_image():
    good = raw_image(RGB, 'rgb8')
    short = Image(header=good.header, height=good.height, width=good.width, encoding='rgb8', step=good.step,
                  data=bytes(good.data)[:-1])
    with pytest.raises(M.BadImage, match='data length 104 does not match step\\*height = 21\\*5 = 105'):
        M.image_to_rgb(short)
    narrow = Image(header=good.header, height=5, width=7, encoding='rgb8', step=20, data=bytes(100))
    with pytest.raises(M.BadImage, match='step 20 is smaller than width'):
        M.image_to_rgb(narrow)
    with pytest.raises(M.BadImage, match='zero size'):
        M.image_to_rgb(Image(encoding='rgb8'))
    assert issubclass(M.BadImage, M.MessageError) and issubclass(M.UnsupportedEncoding, M.MessageError)


# ---------------------------------------------------------------- depth and confidence output
def test_depth_32FC1_keeps_values_and_marks_no_estimate_with_nan():
    d = np.array([[1.25, np.nan, -1.0], [0.0, np.inf, 70.0]], np.float32)
    msg = M.depth_to_image(d, header(), encoding='32FC1')
    assert msg.encoding == '32FC1' and msg.step == 12 and msg.is_bigendian == 0
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1_700_000_000, 123_456_789)
    assert msg.header.frame_id == 'camera_optical_frame'
    raw = np.frombuffer(bytes(msg.data), '<f4').reshape(2, 3)
    assert raw[0, 0] == np.float32(1.25) and raw[1, 2] == np.float32(70.0)
    assert np.isnan(raw[[0, 0, 1, 1], [1, 2, 0, 1]]).all()
    np.testing.assert_array_equal(M.image_to_float(msg), raw)


def test_depth_16UC1_is_rounded_millimetres_zero_for_none_and_clipped():
    d = np.array([[1.2344, 1.2346, np.nan], [-2.0, 70.0, 0.0004]], np.float32)
    msg = M.depth_to_image(d, header(), encoding='16UC1')
    assert msg.encoding == '16UC1' and msg.step == 6
    mm = np.frombuffer(bytes(msg.data), '<u2').reshape(2, 3)
    np.testing.assert_array_equal(mm, [[1234, 1235, 0], [0, 65535, 0]])   # 0.4 mm rounds to 0 = none
    back = M.image_to_float(msg)
    assert back[0, 0] == np.float32(1.234) and np.isnan(back[0, 2])


def test_big_endian_float_images_are_read_correctly():
    d = np.array([[1.5, 2.5]], '>f4')
    msg = Image(header=header(), height=1, width=2, encoding='32FC1', is_bigendian=1, step=8, data=d.tobytes())
    np.testing.assert_array_equal(M.image_to_float(msg), [[1.5, 2.5]])
    mm = np.array([[1500, 0]], '>u2')
    msg16 = Image(header=header(), height=1, width=2, encoding='16UC1', is_bigendian=1, step=4, data=mm.tobytes())
    out = M.image_to_float(msg16)
    assert out[0, 0] == np.float32(1.5) and np.isnan(out[0, 1])


def test_confidence_is_32FC1_in_unit_range():
    c = np.array([[0.25, np.nan, 1.5, -0.1]], np.float32)
    msg = M.confidence_to_image(c, header())
    assert msg.encoding == '32FC1'
    np.testing.assert_array_equal(M.image_to_float(msg), [[0.25, 0.0, 1.0, 0.0]])


def test_depth_encoding_is_checked():
    with pytest.raises(M.UnsupportedEncoding):
        M.depth_to_image(np.ones((2, 2)), header(), encoding='mono8')


# ---------------------------------------------------------------- camera info
K640 = np.array([[500.0, 0.0, 319.5], [0.0, 510.0, 239.5], [0.0, 0.0, 1.0]])


def test_camera_info_round_trip_and_scaling_to_the_output_size():
    K_half = M.scale_K(K640, (640, 480), (320, 240))
    np.testing.assert_allclose(K_half, [[250.0, 0, 159.5], [0, 255.0, 119.5], [0, 0, 1]])  # (319.5+.5)/2-.5
    info = M.K_to_camera_info(K_half, 320, 240, header(frame_id='cam'))
    assert (info.width, info.height, info.distortion_model) == (320, 240, 'plumb_bob')
    assert list(info.d) == [0.0] * 5
    np.testing.assert_allclose(np.reshape(info.p, (3, 4)), np.hstack([K_half, np.zeros((3, 1))]))
    np.testing.assert_allclose(np.reshape(info.r, (3, 3)), np.eye(3))
    assert info.header.frame_id == 'cam' and info.header.stamp.nanosec == 123_456_789
    K, size = M.camera_info_to_K(info)
    np.testing.assert_allclose(K, K_half)
    assert size == (320, 240)
    assert not M.has_distortion(info)
    info.d = [0.1, 0.0, 0.0, 0.0, 0.0]
    assert M.has_distortion(info)


def test_unusable_camera_info_is_rejected_with_a_reason():
    info = M.K_to_camera_info(K640, 640, 480, header())
    info.k = np.zeros(9)
    with pytest.raises(M.BadCameraInfo, match='all zeros'):
        M.camera_info_to_K(info)
    bad = K640.copy()
    bad[0, 0] = -1.0
    info.k = bad.reshape(-1)
    with pytest.raises(M.BadCameraInfo, match='fx=-1, fy=510'):
        M.camera_info_to_K(info)
    bad = K640.copy()
    bad[1, 2] = np.nan
    info.k = bad.reshape(-1)
    with pytest.raises(M.BadCameraInfo, match='non-finite'):
        M.camera_info_to_K(info)


# ---------------------------------------------------------------- poses
def test_odometry_round_trip_and_rejections():
    a = math.radians(30)
    T = make_pose([1.0, -2.0, 0.5], [0.0, 0.0, math.sin(a / 2), math.cos(a / 2)])
    odom = M.matrix_to_odometry(T, header(frame_id='odom'), 'base_link')
    assert odom.child_frame_id == 'base_link' and odom.header.frame_id == 'odom'
    np.testing.assert_allclose(M.odometry_to_matrix(odom), T, atol=1e-12)
    odom.pose.pose.position.x = float('nan')
    with pytest.raises(M.BadOdometry, match='NaN'):
        M.odometry_to_matrix(odom)
    odom.pose.pose.position.x = 1.0
    odom.pose.pose.orientation.w = 2.0
    with pytest.raises(M.BadOdometry, match='not a unit quaternion'):
        M.odometry_to_matrix(odom)
    odom.pose.pose.orientation.w = 0.0
    odom.pose.pose.orientation.z = 0.0
    with pytest.raises(M.BadOdometry, match='norm 0'):
        M.odometry_to_matrix(odom)


def test_pose_stamped_round_trip():
    T = make_pose([0.1, 0.2, 0.3], [0.5, 0.5, 0.5, 0.5])
    msg = M.matrix_to_pose_stamped(T, header(frame_id='odom'))
    assert msg.header.frame_id == 'odom'
    np.testing.assert_allclose(M.pose_msg_to_matrix(msg), T, atol=1e-12)


# ---------------------------------------------------------------- stamps
def test_stamps_are_exact_integers():
    ns = 1_700_000_000_123_456_789
    t = M.ns_to_stamp(ns)
    assert (t.sec, t.nanosec) == (1_700_000_000, 123_456_789)
    assert M.stamp_to_ns(t) == ns
    assert M.stamp_to_ns(M.ns_to_stamp(-1)) == -1
    h = M.copy_header(header(sec=3, nanosec=7, frame_id='x'))
    assert (h.stamp.sec, h.stamp.nanosec, h.frame_id) == (3, 7, 'x')
    h2 = M.make_header(3_000_000_007, 'x')
    assert h2 == h


# ---------------------------------------------------------------- point clouds
def test_point_cloud_xyzrgb_organised_with_nan_points():
    K = np.array([[100.0, 0, 2.0], [0, 50.0, 1.0], [0, 0, 1]])
    depth = np.full((3, 4), np.nan, np.float32)
    depth[0, 3] = 2.0
    depth[2, 0] = 4.0
    rgb = np.zeros((3, 4, 3), np.uint8)
    rgb[0, 3] = (255, 16, 1)
    msg = M.depth_to_pointcloud(depth, rgb, K, header(frame_id='cam'))
    assert (msg.height, msg.width, msg.point_step, msg.row_step) == (3, 4, 16, 64)
    assert msg.is_dense is False and msg.header.frame_id == 'cam'
    assert [(f.name, f.offset, f.datatype, f.count) for f in msg.fields] == [
        ('x', 0, 7, 1), ('y', 4, 7, 1), ('z', 8, 7, 1), ('rgb', 12, 7, 1)]
    xyz, colours = M.pointcloud_to_xyzrgb(msg)
    assert xyz.shape == (12, 3)
    np.testing.assert_allclose(xyz[3], [(3 - 2.0) / 100 * 2.0, (0 - 1.0) / 50 * 2.0, 2.0], rtol=1e-6)
    np.testing.assert_allclose(xyz[8], [(0 - 2.0) / 100 * 4.0, (2 - 1.0) / 50 * 4.0, 4.0], rtol=1e-6)
    assert np.isnan(xyz[[0, 1, 2, 4]]).all()
    np.testing.assert_array_equal(colours[3], [255, 16, 1])
    bits = np.frombuffer(bytes(msg.data), np.uint8).reshape(12, 16)[3, 12:16].view('<u4')[0]
    assert bits == 0x00FF1001


def test_point_cloud_can_skip_invalid_points():
    K = np.array([[10.0, 0, 0], [0, 10.0, 0], [0, 0, 1]])
    depth = np.array([[1.0, np.nan], [0.0, 2.0]], np.float32)
    msg = M.depth_to_pointcloud(depth, np.zeros((2, 2, 3), np.uint8), K, header(), skip_invalid=True)
    assert (msg.height, msg.width, msg.is_dense) == (1, 2, True)
    xyz, _ = M.pointcloud_to_xyzrgb(msg)
    np.testing.assert_allclose(xyz, [[0, 0, 1], [0.2, 0.2, 2]])
    with pytest.raises(ValueError, match='sizes differ'):
        M.depth_to_pointcloud(depth, np.zeros((3, 2, 3), np.uint8), K, header())
