"""dpv_sensor.ros.msgs: ROS messages <-> numpy, exact stamps and frame ids, and the specific errors for bad input."""
import math

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from sensor_msgs.msg import Image
from std_msgs.msg import Header

from dpv_sensor.ros import msgs as M
from dpv_sensor.ros import pose_msgs as PM
from dpv_sensor.ros import cloud_msgs as C
from dpv_sensor.ros import compressed_depth as CD
from dpv_sensor.core.odometry_covariance import NOT_FINITE
from dpv_sensor.stream.pose_buffer import make_pose

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


@pytest.mark.parametrize('pad', [0, 3])
@pytest.mark.parametrize('delta, ok', [(0, True), (-1, False), (1, False), (-21, False), (21, False)])
def test_the_receipt_check_wants_exactly_step_times_height_bytes(pad, delta, ok):
    """Either side of the rule: exactly step*height bytes pass (with or without row padding); one byte short or
    over, or a whole row short or over, is refused by the check the subscription callback runs (and by the
    conversion, which shares it)."""
    good = raw_image(RGB, 'rgb8', pad=pad)
    data = bytes(good.data) + bytes(max(delta, 0)) if delta >= 0 else bytes(good.data)[:delta]
    msg = Image(header=good.header, height=good.height, width=good.width, encoding='rgb8', step=good.step,
                data=data)
    if ok:
        assert M.check_colour_image(msg) == (3, (0, 1, 2))
        np.testing.assert_array_equal(M.image_to_rgb(msg), RGB)
        return
    n, want = len(data), good.step * good.height
    for check in (M.check_colour_image, M.image_to_rgb):
        with pytest.raises(M.BadImage, match=f'data length {n} does not match step\\*height = '
                                             f'{good.step}\\*5 = {want}'):
            check(msg)


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
    odom = PM.matrix_to_odometry(T, header(frame_id='odom'), 'base_link')
    assert odom.child_frame_id == 'base_link' and odom.header.frame_id == 'odom'
    np.testing.assert_allclose(PM.odometry_to_matrix(odom), T, atol=1e-12)
    odom.pose.pose.position.x = float('nan')
    with pytest.raises(M.BadOdometry, match='NaN'):
        PM.odometry_to_matrix(odom)
    odom.pose.pose.position.x = 1.0
    odom.pose.pose.orientation.w = 2.0
    with pytest.raises(M.BadOdometry, match='not a unit quaternion'):
        PM.odometry_to_matrix(odom)
    odom.pose.pose.orientation.w = 0.0
    odom.pose.pose.orientation.z = 0.0
    with pytest.raises(M.BadOdometry, match='norm 0'):
        PM.odometry_to_matrix(odom)


def test_odometry_covariance_filled_or_not():
    odom = PM.matrix_to_odometry(np.eye(4), header(frame_id='odom'), 'base_link', position_sigma=0.1,
                                rotation_sigma=0.02)
    cov = PM.odometry_covariance(odom)
    np.testing.assert_allclose(np.diag(cov), [0.01] * 3 + [0.0004] * 3)
    assert PM.odometry_covariance(PM.matrix_to_odometry(np.eye(4), header(frame_id='odom'), 'base_link')) is None


def test_odometry_covariance_with_nan_anywhere_is_not_used_and_is_told_apart_from_an_unfilled_one():
    odom = PM.matrix_to_odometry(np.eye(4), header(frame_id='odom'), 'base_link', position_sigma=0.1,
                                rotation_sigma=0.02)
    assert PM.odometry_covariance_checks(odom)[0].problem is None
    cov = list(odom.pose.covariance)
    cov[1] = float('nan')                      # off the diagonal: the diagonal alone looks filled
    odom.pose.covariance = cov
    assert PM.odometry_covariance(odom) is None and PM.odometry_covariance_checks(odom)[0].problem == NOT_FINITE
    unfilled = PM.matrix_to_odometry(np.eye(4), header(frame_id='odom'), 'base_link')
    assert PM.odometry_covariance_checks(unfilled)[0].problem is None


def test_pose_stamped_round_trip():
    T = make_pose([0.1, 0.2, 0.3], [0.5, 0.5, 0.5, 0.5])
    msg = PM.matrix_to_pose_stamped(T, header(frame_id='odom'))
    assert msg.header.frame_id == 'odom'
    np.testing.assert_allclose(PM.pose_msg_to_matrix(msg), T, atol=1e-12)


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
    msg = C.depth_to_pointcloud(depth, rgb, K, header(frame_id='cam'))
    assert (msg.height, msg.width, msg.point_step, msg.row_step) == (3, 4, 16, 64)
    assert msg.is_dense is False and msg.header.frame_id == 'cam'
    assert [(f.name, f.offset, f.datatype, f.count) for f in msg.fields] == [
        ('x', 0, 7, 1), ('y', 4, 7, 1), ('z', 8, 7, 1), ('rgb', 12, 7, 1)]
    xyz, colours = C.pointcloud_to_xyzrgb(msg)
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
    msg = C.depth_to_pointcloud(depth, np.zeros((2, 2, 3), np.uint8), K, header(), skip_invalid=True)
    assert (msg.height, msg.width, msg.is_dense) == (1, 2, True)
    xyz, _ = C.pointcloud_to_xyzrgb(msg)
    np.testing.assert_allclose(xyz, [[0, 0, 1], [0.2, 0.2, 2]])
    with pytest.raises(ValueError, match='sizes differ'):
        C.depth_to_pointcloud(depth, np.zeros((3, 2, 3), np.uint8), K, header())


# ---- compressedDepth (image_transport's PNG flavour) and the decimated cloud -------------------------------------
def _png_payload(msg):
    import cv2
    data = bytes(msg.data)
    assert data[12:20] == b'\x89PNG\r\n\x1a\n'               # the PNG starts right after the 12-byte header
    return cv2.imdecode(np.frombuffer(data[12:], np.uint8), cv2.IMREAD_UNCHANGED)


def test_compressed_depth_32fc1_is_quantised_inverse_depth_with_the_plugin_header():
    import struct
    depth = np.array([[1.0, 2.0, 3.0], [np.nan, 12.0, 10.0]], np.float32)
    msg = CD.depth_to_compressed_depth(depth, header(frame_id='cam'), encoding='32FC1')
    assert msg.format == '32FC1; compressedDepth png'
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id) == (1_700_000_000, 123_456_789, 'cam')
    # defaults depth_max 10, depth_quantization 100: a = 100 * 101 = 10100, b = 1 - 10100 / 10 = -1009
    assert bytes(msg.data[:12]) == struct.pack('<iff', 0, 10100.0, -1009.0)
    # q = trunc(10100 / d - 1009): 1 m -> 9091, 2 m -> 4041, 3 m -> 2357 (2357.67); NaN and d >= 10 m -> 0
    np.testing.assert_array_equal(_png_payload(msg), [[9091, 4041, 2357], [0, 0, 0]])
    back = CD.compressed_depth_to_float(msg)
    assert back.dtype == np.float32 and back.shape == (2, 3)
    assert back[0, 0] == 1.0 and back[0, 1] == 2.0                   # 10100 / (9091 + 1009), 10100 / 5050
    assert back[0, 2] == pytest.approx(10100 / 3366, rel=1e-6)       # 3.0006: the truncation's step at 3 m
    assert np.isnan(back[1]).all()


def test_compressed_depth_16uc1_is_millimetres_cut_at_depth_max():
    import struct
    depth = np.array([[1.5, 0.0004, 10.0, 10.0006, -1.0]], np.float32)
    msg = CD.depth_to_compressed_depth(depth, 5, 'cam', encoding='16UC1', png_level=1)
    assert msg.format == '16UC1; compressedDepth png'
    assert bytes(msg.data[:12]) == struct.pack('<iff', 0, 0.0, 0.0)
    np.testing.assert_array_equal(_png_payload(msg), [[1500, 0, 10000, 0, 0]])   # 10001 mm > 10000: cut
    back = CD.compressed_depth_to_float(msg)
    np.testing.assert_array_equal(back, np.array([[1.5, np.nan, 10.0, np.nan, np.nan]], np.float32))


def test_compressed_depth_round_trip_within_the_quantisation_and_other_settings():
    rng = np.random.default_rng(3)
    depth = rng.uniform(0.3, 4.0, (24, 32)).astype(np.float32)
    depth[0, :5] = np.nan
    msg = CD.depth_to_compressed_depth(depth, header(), encoding='32FC1', depth_max=5.0, depth_quantization=50.0)
    back = CD.compressed_depth_to_float(msg)
    a = 50.0 * 51.0
    ok = np.isfinite(depth)
    assert np.isnan(back[~ok]).all() and np.isfinite(back[ok]).all()
    # one code step at depth d is d^2 / a (relative error d / a): truncation only ever moves depth further
    err = back[ok] - depth[ok]
    assert (err >= -1e-5).all() and (err <= depth[ok] ** 2 / a * 1.01 + 1e-5).all()
    legacy = M.ROS('sensor_msgs/msg/CompressedImage', header=msg.header, format='32FC1', data=msg.data)
    np.testing.assert_array_equal(CD.compressed_depth_to_float(legacy), back)    # the plugin's old format string
    with pytest.raises(M.UnsupportedEncoding, match='only PNG'):
        CD.compressed_depth_to_float(M.ROS('sensor_msgs/msg/CompressedImage', header=msg.header,
                                          format='32FC1; compressedDepth rvl', data=msg.data))
    with pytest.raises(M.BadImage, match='holds no image'):
        CD.compressed_depth_to_float(M.ROS('sensor_msgs/msg/CompressedImage', header=msg.header,
                                          format='16UC1; compressedDepth png', data=bytes(12)))
    with pytest.raises(M.UnsupportedEncoding):
        CD.depth_to_compressed_depth(depth, header(), encoding='mono8')


def test_decimated_cloud_keeps_the_full_clouds_points():
    rng = np.random.default_rng(5)
    depth = rng.uniform(0.5, 3.0, (7, 10)).astype(np.float32)
    depth[3, 3] = np.nan                                     # kept by the grid: a NaN point at (1, 1)
    rgb = rng.integers(0, 256, (7, 10, 3), dtype=np.uint8)
    K = np.array([[8.0, 0, 4.5], [0, 9.0, 3.5], [0, 0, 1]])
    full_xyz, full_rgb = C.pointcloud_to_xyzrgb(C.depth_to_pointcloud(depth, rgb, K, header()))
    msg = C.depth_to_pointcloud_decimated(depth, rgb, K, header(frame_id='cam'), decimation=3)
    assert (msg.height, msg.width, msg.is_dense, msg.header.frame_id) == (3, 4, False, 'cam')   # ceil(7/3), ceil(10/3)
    xyz, colours = C.pointcloud_to_xyzrgb(msg)
    idx = (np.arange(0, 7, 3)[:, None] * 10 + np.arange(0, 10, 3)[None, :]).reshape(-1)
    np.testing.assert_allclose(xyz, full_xyz[idx], rtol=1e-6, equal_nan=True)
    np.testing.assert_array_equal(colours, full_rgb[idx])
    # pixel (6, 9) at depth d: x = (9 - 4.5) / 8 * d, y = (6 - 3.5) / 9 * d
    d = depth[6, 9]
    np.testing.assert_allclose(xyz[-1], [4.5 / 8 * d, 2.5 / 9 * d, d], rtol=1e-6)
    assert np.isnan(xyz[1 * 4 + 1]).all() and np.isfinite(xyz[1 * 4 + 2]).all()
    assert C.depth_to_pointcloud_decimated(depth, rgb, K, header()).width == 10
    with pytest.raises(ValueError, match='positive integer'):
        C.depth_to_pointcloud_decimated(depth, rgb, K, header(), decimation=0)
