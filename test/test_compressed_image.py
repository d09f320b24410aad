"""dpv_sensor.ros.compressed_image: image_transport's compressed colour images (JPEG / PNG) decode to the raw image's
fields with the right channel order, the format field is honoured, and a payload that cannot be decoded raises the
specific UndecodableImage (and, on receipt, is counted as undecodable_image with a log line naming stamp and why)."""
import collections

import cv2
import numpy as np
import pytest
from builtin_interfaces.msg import Time
from sensor_msgs.msg import CompressedImage
from std_msgs.msg import Header

from dpv_sensor.ros import compressed_image as CI
from dpv_sensor.ros import msgs as M
from dpv_sensor.ros.receipt import ImageReceipt


def smooth_rgb(h=48, w=64) -> np.ndarray:
    """A smooth colour image (JPEG keeps it within a few grey levels), distinct in every channel."""
    y, x = np.mgrid[0:h, 0:w]
    return np.stack([x * 255 // (w - 1), y * 255 // (h - 1), (x + y) * 255 // (w + h - 2)], -1).astype(np.uint8)


RGB = smooth_rgb()


def header(sec=1_700_000_000, nanosec=5, frame_id='cam_optical'):
    return Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=frame_id)


def compressed(data: bytes, fmt: str) -> CompressedImage:
    return CompressedImage(header=header(), format=fmt, data=data)


def encoded(px, ext: str, *params) -> bytes:
    ok, buf = cv2.imencode(ext, px, list(params))
    assert ok
    return buf.tobytes()


@pytest.mark.parametrize('codec,tolerance', [('jpeg', 6.0), ('png', 0.0)])
@pytest.mark.parametrize('encoding', ['rgb8', 'bgr8', 'rgba8'])
def test_round_trip_through_the_plugins_format(codec, tolerance, encoding):
    msg = CI.rgb_to_compressed(RGB, header(), codec=codec, encoding=encoding)
    assert msg.format == f'{encoding}; {codec} compressed bgr8'
    out = CI.compressed_to_rgb(msg)
    assert out.shape == RGB.shape and out.dtype == np.uint8
    err = np.abs(out.astype(int) - RGB.astype(int))
    assert err.mean() <= tolerance / 3 and err.max() <= 8 * max(tolerance, 0.125), (codec, err.mean(), err.max())
    decoded = CI.decode_message(msg)
    assert decoded.error is None and decoded.encoding == 'bgr8' and (decoded.width, decoded.height) == (64, 48)
    assert decoded.header.stamp.nanosec == 5 and decoded.header.frame_id == 'cam_optical'


def test_channel_order_is_not_swapped():
    """Pure red stays red (a BGR/RGB mix-up would turn it blue)."""
    red = np.zeros((16, 16, 3), np.uint8)
    red[..., 0] = 255
    for codec in ('jpeg', 'png'):
        out = CI.compressed_to_rgb(CI.rgb_to_compressed(red, header(), codec=codec))
        assert out[..., 0].min() > 240 and out[..., 2].max() < 15, codec


@pytest.mark.parametrize('fmt', ['jpeg', 'png', '', 'bgr8; jpeg compressed bgr8', 'rgb8; png compressed bgr8'])
def test_older_and_empty_formats_read_the_payload(fmt):
    codec = 'png' if 'png' in fmt else 'jpeg'
    data = encoded(RGB[:, :, ::-1], '.png' if codec == 'png' else '.jpg', cv2.IMWRITE_JPEG_QUALITY, 95)
    out = CI.compressed_to_rgb(compressed(data, fmt))
    assert np.abs(out.astype(int) - RGB.astype(int)).mean() < 3


def test_a_target_in_rgb_order_is_honoured():
    """'rgb8; png compressed rgb8': the compressed pixels are already RGB; no swap."""
    data = encoded(RGB, '.png')           # RGB bytes stored as they are
    np.testing.assert_array_equal(CI.compressed_to_rgb(compressed(data, 'rgb8; png compressed rgb8')), RGB)
    assert CI.decode_message(compressed(data, 'rgb8; png compressed rgb8')).encoding == 'rgb8'


@pytest.mark.parametrize('codec', ['jpeg', 'png'])
def test_mono_decodes_to_grey_rgb(codec):
    msg = CI.rgb_to_compressed(RGB, header(), codec=codec, encoding='mono8')
    assert msg.format == f'mono8; {codec} compressed mono8'
    decoded = CI.decode_message(msg)
    assert decoded.encoding == 'mono8' and decoded.step == 64
    out = M.image_to_rgb(decoded)
    assert out.shape == RGB.shape
    np.testing.assert_array_equal(out[..., 0], out[..., 2])
    grey = cv2.cvtColor(RGB, cv2.COLOR_RGB2GRAY).astype(int)
    assert np.abs(out[..., 1].astype(int) - grey).mean() < 3


def test_png_with_alpha_decodes_to_rgb():
    bgra = np.concatenate([RGB[:, :, ::-1], np.full(RGB.shape[:2] + (1,), 7, np.uint8)], 2)
    decoded = CI.decode_message(compressed(encoded(bgra, '.png'), 'bgra8; png compressed bgra8'))
    assert decoded.encoding == 'bgra8'
    np.testing.assert_array_equal(M.image_to_rgb(decoded), RGB)


JPEG = encoded(RGB[:, :, ::-1], '.jpg', cv2.IMWRITE_JPEG_QUALITY, 90)
PNG = encoded(RGB[:, :, ::-1], '.png')


@pytest.mark.parametrize('fmt,data,why', [
    ('rgb8; jpeg compressed bgr8', JPEG[:len(JPEG) // 2], 'truncated JPEG'),
    ('rgb8; jpeg compressed bgr8', JPEG[:-2], 'truncated JPEG'),
    ('rgb8; png compressed bgr8', PNG[:len(PNG) - 20], 'cannot decode'),
    ('rgb8; jpeg compressed bgr8', b'\x00garbage bytes, not an image', 'neither JPEG nor PNG'),
    ('rgb8; jpeg compressed bgr8', b'', 'neither JPEG nor PNG'),
    ('rgb8; png compressed bgr8', JPEG, 'says PNG'),
    ('16UC1; compressedDepth png', PNG, 'unsupported compressed image format'),
    ('rgb8; tiff compressed bgr8', PNG, 'unsupported compressed image format'),
    ('mono16; png compressed mono16', encoded(np.full((4, 4), 1000, np.uint16), '.png'), '16-bit'),
])
def test_undecodable_payloads_raise_the_specific_error(fmt, data, why):
    with pytest.raises(CI.UndecodableImage, match=why):
        CI.decode_compressed(fmt, data)
    decoded = CI.decode_message(compressed(data, fmt))      # on receipt: never raises
    assert isinstance(decoded.error, CI.UndecodableImage) and decoded.height == decoded.width == 0
    assert decoded.compressed_bytes == len(data)


def test_jpeg_with_trailing_padding_still_decodes():
    assert CI.compressed_to_rgb(compressed(JPEG + b'\x00\x00', 'jpeg')).shape == RGB.shape


def test_image_message_to_rgb_takes_raw_and_compressed():
    raw = M.rgb_to_image(RGB, header())
    np.testing.assert_array_equal(CI.image_message_to_rgb(raw), RGB)
    np.testing.assert_array_equal(CI.image_message_to_rgb(CI.rgb_to_compressed(RGB, header(), codec='png')), RGB)


class _Faults:
    def __init__(self):
        self.counts = collections.Counter()
        self.lines = []

    def report(self, kind, message, **_kw):
        self.counts[kind] += 1
        self.lines.append(message)


def test_receipt_counts_an_undecodable_image_and_passes_the_next_good_one():
    faults, dropped = _Faults(), collections.Counter()
    receipt = ImageReceipt(faults, lambda reason: dropped.update([reason]))
    bad = CI.decode_message(compressed(JPEG[:100], 'rgb8; jpeg compressed bgr8'))
    assert receipt.image(bad, 1_700_000_000_000_000_005, None, 0.0, 0) is None
    assert dropped == {CI.UNDECODABLE_IMAGE: 1} and faults.counts[CI.UNDECODABLE_IMAGE] == 1
    line = faults.lines[-1]
    assert '1700000000.000 s' in line and 'truncated JPEG' in line and "format 'rgb8; jpeg compressed bgr8'" in line
    good = CI.decode_message(compressed(JPEG, 'rgb8; jpeg compressed bgr8'))
    item = receipt.image(good, 1_700_000_000_033_000_000, 33_000_000, 0.0, 0)
    assert item is not None and item.msg is good and M.image_to_rgb(item.msg).shape == RGB.shape


def test_the_decode_benchmark_runs_and_reports_both_codecs():
    from dpv_sensor.benchmarks import image_decode
    res = image_decode.run(width=64, height=48, repeats=3)
    assert set(res['codecs']) == {'jpeg', 'png'} and res['codecs']['png']['mean_abs_error'] == 0.0
    assert res['codecs']['jpeg']['decode']['median_ms'] > 0 and '| jpeg | quality 90 |' in image_decode.table(res)


# ---------------------------------------------------------------- every channel order, raw and compressed
def banded_channels(h=12, w=10, seed=3):
    """R, G, B and alpha from disjoint value bands (R < 64 <= G < 128 <= B < 192 <= A): any swap or an alpha read
    as colour changes every pixel."""
    rng = np.random.default_rng(seed)
    bands = [rng.integers(64 * k, 64 * (k + 1), (h, w), dtype=np.uint8) for k in range(4)]
    return np.stack(bands[:3], -1), bands[3][..., None]


CH_RGB, CH_ALPHA = banded_channels()
GREY = CH_RGB[..., 1:2].copy()


def raw_message(encoding: str):
    from sensor_msgs.msg import Image
    px = {'rgb8': CH_RGB, 'bgr8': CH_RGB[..., ::-1], 'rgba8': np.concatenate([CH_RGB, CH_ALPHA], 2),
          'bgra8': np.concatenate([CH_RGB[..., ::-1], CH_ALPHA], 2), 'mono8': GREY}[encoding]
    px = np.ascontiguousarray(px)
    h, w, c = px.shape
    return Image(header=header(), height=h, width=w, encoding=encoding, step=w * c, data=px.tobytes())


# (format as the publisher wrote it, the pixels it handed to the PNG encoder (OpenCV takes them as B, G, R[, A]))
PNG_CASES = {
    'rgb8 -> bgr8': ('rgb8; png compressed bgr8', CH_RGB[..., ::-1]),
    'bgr8 -> bgr8': ('bgr8; png compressed bgr8', CH_RGB[..., ::-1]),
    'rgb8 -> rgb8': ('rgb8; png compressed rgb8', CH_RGB),
    'rgba8 -> rgba8': ('rgba8; png compressed rgba8', np.concatenate([CH_RGB, CH_ALPHA], 2)),
    'rgba8 -> bgra8': ('rgba8; png compressed bgra8', np.concatenate([CH_RGB[..., ::-1], CH_ALPHA], 2)),
    'bgra8 -> bgra8': ('bgra8; png compressed bgra8', np.concatenate([CH_RGB[..., ::-1], CH_ALPHA], 2)),
    'bgra8 -> rgba8': ('bgra8; png compressed rgba8', np.concatenate([CH_RGB, CH_ALPHA], 2)),
    'RGBA file, format png': ('png', np.concatenate([CH_RGB[..., ::-1], CH_ALPHA], 2)),
    'RGBA file, no format': ('', np.concatenate([CH_RGB[..., ::-1], CH_ALPHA], 2)),
    'RGB file, format png': ('png', CH_RGB[..., ::-1]),
    'mono8 -> mono8': ('mono8; png compressed mono8', GREY),
}


@pytest.mark.parametrize('encoding', ['rgb8', 'bgr8', 'rgba8', 'bgra8', 'mono8'])
def test_every_raw_channel_order_decodes_to_exactly_its_rgb(encoding):
    out = M.image_to_rgb(raw_message(encoding))
    expected = np.repeat(GREY, 3, 2) if encoding == 'mono8' else CH_RGB
    np.testing.assert_array_equal(out, expected, err_msg=encoding)


@pytest.mark.parametrize('case', sorted(PNG_CASES))
def test_every_compressed_png_channel_order_decodes_to_exactly_its_rgb_through_the_receipt(case):
    """A PNG with and without alpha in every order a publisher writes it: exactly the RGB that was sent (PNG is
    lossless), the alpha never read as a colour, through the path the node takes (header size, decode, receipt)."""
    fmt, px = PNG_CASES[case]
    msg = compressed(encoded(np.ascontiguousarray(px), '.png'), fmt)
    assert CI.compressed_size(msg.data) == (px.shape[1], px.shape[0])
    faults, dropped = _Faults(), collections.Counter()
    item = ImageReceipt(faults, lambda reason: dropped.update([reason])).image(
        msg, 1_700_000_000_000_000_000, 0.0, 0, decode=CI.decode_message)
    assert item is not None and not dropped, faults.lines
    expected = np.repeat(GREY, 3, 2) if px.shape[2] == 1 else CH_RGB
    np.testing.assert_array_equal(M.image_to_rgb(item.msg), expected, err_msg=case)
    np.testing.assert_array_equal(CI.compressed_to_rgb(msg), expected, err_msg=case)


@pytest.mark.parametrize('encoding', ['rgb8', 'bgr8', 'rgba8', 'bgra8'])
def test_every_colour_order_through_a_jpeg_keeps_its_channels(encoding):
    """JPEG (lossy, no alpha) as image_transport's plugin writes each colour encoding: every channel stays in its
    band (a swap would move it by 64 grey levels or more)."""
    smooth = cv2.GaussianBlur(CH_RGB, (5, 5), 0)
    out = CI.compressed_to_rgb(CI.rgb_to_compressed(smooth, header(), codec='jpeg', jpeg_quality=98,
                                                    encoding=encoding))
    assert np.abs(out.astype(int) - smooth.astype(int)).max() < 32, encoding
