"""image_transport's ``compressed`` colour images (sensor_msgs/CompressedImage, JPEG or PNG) <-> numpy, with OpenCV
(no rclpy import; message flavours as in ``msgs``).

The node subscribes ``<image topic>/compressed`` with ``image_transport: compressed`` and decodes each message on
receipt into a :class:`DecodedImage`, which reads like a sensor_msgs/Image (header, encoding, height, width, step,
data), so that the receipt checks, the stream-loss accounting and the worker treat it exactly as a raw image. A
payload that cannot be decoded becomes a DecodedImage carrying the :class:`UndecodableImage` error instead of pixels
(the receipt counts and logs it: faults.undecodable_image, dropped.undecodable_image).

The ``format`` field, as image_transport's compressed plugin writes it: ``'<encoding>; <jpeg|png> compressed
<target>'`` (e.g. ``'rgb8; jpeg compressed bgr8'``, ``'mono8; png compressed mono8'``), or the older ``'jpeg'`` /
``'png'``; an empty format is read by the payload's signature. OpenCV decodes a colour JPEG or PNG to BGR (BGRA with
alpha) and a grey one to one channel; a target ``rgb8`` / ``rgba8`` says the publisher's channels were already in
RGB order. compressedDepth, 16-bit PNG and other codecs are not colour input and are refused.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dpv_sensor.ros.msgs import ROS, MessageError, MessageTypes, header_for

UNDECODABLE_IMAGE = 'undecodable_image'      # the fault kind and drop reason (faults.*, dropped.* in /diagnostics)
CODECS = ('jpeg', 'png')
JPEG_SIGNATURE = b'\xff\xd8\xff'
PNG_SIGNATURE = b'\x89PNG\r\n\x1a\n'
JPEG_END = b'\xff\xd9'
_ALIASES = {'jpg': 'jpeg', 'jpeg': 'jpeg', 'png': 'png'}


class UndecodableImage(MessageError):
    """A compressed image the node cannot decode (truncated or garbage payload, unsupported format); the text says
    why."""


@dataclass(frozen=True)
class CompressedFormat:
    """A parsed ``format`` field: the codec ('jpeg', 'png' or '' when the field does not say), the publisher's
    encoding ('' when not given) and the channel order of the compressed pixels ('' when not given)."""
    codec: str
    encoding: str = ''
    target: str = ''


@dataclass
class DecodedImage:
    """A decoded compressed image in the fields of a sensor_msgs/Image (``msgs.image_to_rgb`` and
    ``msgs.check_colour_image`` read it as one); ``error`` is set (and the image empty) when decoding failed.
    ``format`` and ``compressed_bytes`` say what arrived."""
    header: object
    encoding: str
    height: int
    width: int
    step: int
    data: np.ndarray
    format: str
    compressed_bytes: int
    error: UndecodableImage | None = None


def parse_format(fmt: str) -> CompressedFormat:
    """image_transport's ``format`` field -> CompressedFormat. Raises UndecodableImage for a codec other than JPEG
    or PNG (compressedDepth, rvl, ...)."""
    text = str(fmt).strip()
    encoding, sep, rest = text.partition(';')
    if not sep:                              # 'jpeg', 'png', '' (older publishers): the codec alone
        rest, encoding = text, ''
    words = rest.strip().lower().split()
    if not words:
        return CompressedFormat('', encoding.strip())
    codec = _ALIASES.get(words[0])
    if codec is None or (len(words) > 1 and words[1] != 'compressed'):
        raise UndecodableImage(f"unsupported compressed image format '{fmt}' (the colour input reads image_transport's "
                               "compressed JPEG or PNG, e.g. 'rgb8; jpeg compressed bgr8')")
    target = words[2] if len(words) > 2 else ''
    return CompressedFormat(codec, encoding.strip(), target)


def _sniff(data: bytes) -> str:
    if data.startswith(JPEG_SIGNATURE):
        return 'jpeg'
    if data.startswith(PNG_SIGNATURE):
        return 'png'
    return ''


# JPEG start-of-frame markers (baseline, extended, progressive, lossless; Huffman and arithmetic): they carry the size
_JPEG_SOF = frozenset({0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF})
# markers without a length field
_JPEG_STANDALONE = frozenset({0x01, *range(0xD0, 0xD8)})


def compressed_size(data) -> tuple[int, int] | None:
    """(width, height) of a JPEG or PNG payload read from its header (the PNG IHDR chunk, the JPEG start-of-frame
    segment) without decoding the pixels, or None when the header does not say (not JPEG / PNG, truncated before
    the size, a malformed segment). The node judges a compressed image's size on receipt with it, so that an image
    it refuses for its size is never decoded."""
    try:
        payload = memoryview(data).cast('B')          # bytes, array('B'), a uint8 array: no copy
    except (TypeError, ValueError):
        payload = memoryview(bytes(data))
    head = bytes(payload[:8])
    if head == PNG_SIGNATURE:
        if len(payload) < 24 or bytes(payload[12:16]) != b'IHDR':
            return None
        return int.from_bytes(payload[16:20], 'big'), int.from_bytes(payload[20:24], 'big')
    if not head.startswith(JPEG_SIGNATURE):
        return None
    i, n = 2, len(payload)
    while i + 4 <= n:
        if payload[i] != 0xFF:
            return None
        marker = payload[i + 1]
        if marker == 0xFF:                  # fill byte before a marker
            i += 1
            continue
        if marker in _JPEG_STANDALONE:
            i += 2
            continue
        if marker in (0xD9, 0xDA):          # end of image, start of scan: no frame header before it
            return None
        length = int.from_bytes(payload[i + 2:i + 4], 'big')
        if length < 2:
            return None
        if marker in _JPEG_SOF:
            if length < 7 or i + 9 > n:
                return None
            height = int.from_bytes(payload[i + 5:i + 7], 'big')
            width = int.from_bytes(payload[i + 7:i + 9], 'big')
            return width, height
        i += 2 + length
    return None


def decode_compressed(fmt: str, data) -> tuple[np.ndarray, str]:
    """(pixels HxWxC uint8, encoding 'bgr8' / 'rgb8' / 'bgra8' / 'rgba8' / 'mono8') of a compressed colour image.

    Raises UndecodableImage for an unsupported format, a payload that is not the format's codec, a truncated JPEG
    (no end-of-image marker), anything OpenCV cannot decode and a decoded image that is not 8-bit colour or grey.
    """
    import cv2
    parsed = parse_format(fmt)
    payload = bytes(data)
    n = len(payload)
    found = _sniff(payload)
    if not found:
        head = payload[:8].hex(' ') or 'nothing'
        raise UndecodableImage(f'the {n}-byte payload is neither JPEG nor PNG (starts with {head})')
    if parsed.codec and found != parsed.codec:
        raise UndecodableImage(f"format '{fmt}' says {parsed.codec.upper()} but the {n}-byte payload is a "
                               f'{found.upper()}')
    if found == 'jpeg' and not payload.rstrip(b'\x00').endswith(JPEG_END):
        raise UndecodableImage(f'truncated JPEG: the {n}-byte payload has no end-of-image marker')
    try:
        px = cv2.imdecode(np.frombuffer(payload, np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:
        raise UndecodableImage(f'OpenCV cannot decode the {n}-byte {found.upper()} payload: '
                               f'{str(exc).strip().splitlines()[-1]}') from None
    if px is None:
        raise UndecodableImage(f'OpenCV cannot decode the {n}-byte {found.upper()} payload (truncated or corrupt)')
    if px.dtype != np.uint8:
        raise UndecodableImage(f'the {found.upper()} holds a {px.dtype} image; the colour input needs 8 bits per '
                               'channel (a 16-bit PNG is depth or mono16)')
    if px.ndim == 2 or px.shape[2] == 1:
        return px.reshape(px.shape[0], px.shape[1], 1), 'mono8'
    channels = px.shape[2]
    if channels not in (3, 4):
        raise UndecodableImage(f'the {found.upper()} decodes to {channels} channels (expected 1, 3 or 4)')
    rgb_order = parsed.target in ('rgb8', 'rgba8')
    return px, ('rgb' if rgb_order else 'bgr') + ('8' if channels == 3 else 'a8')


def decode_message(msg) -> DecodedImage:
    """A received sensor_msgs/CompressedImage (any flavour) -> DecodedImage; never raises: a payload that cannot
    be decoded gives an empty image with ``error`` set."""
    data = msg.data
    fmt = str(msg.format)
    try:
        px, encoding = decode_compressed(fmt, data)
    except UndecodableImage as exc:
        return DecodedImage(msg.header, '', 0, 0, 0, np.zeros(0, np.uint8), fmt, len(data), exc)
    h, w, c = px.shape
    return DecodedImage(msg.header, encoding, h, w, w * c, np.ascontiguousarray(px).reshape(-1), fmt, len(data))


def compressed_to_rgb(msg) -> np.ndarray:
    """A sensor_msgs/CompressedImage (JPEG or PNG colour) -> HxWx3 uint8 RGB. Raises UndecodableImage."""
    from dpv_sensor.ros.msgs import image_to_rgb
    decoded = decode_message(msg)
    if decoded.error is not None:
        raise decoded.error
    return image_to_rgb(decoded)


def image_message_to_rgb(msg) -> np.ndarray:
    """A colour sensor_msgs/Image or CompressedImage (any flavour) -> HxWx3 uint8 RGB."""
    from dpv_sensor.ros.msgs import image_to_rgb
    if hasattr(msg, 'format') and not hasattr(msg, 'encoding'):
        return compressed_to_rgb(msg)
    return image_to_rgb(msg)


def rgb_to_compressed(rgb_hw3, header, frame_id: str | None = None, codec: str = 'jpeg', jpeg_quality: int = 90,
                      encoding: str = 'rgb8', png_level: int = 3, types: MessageTypes = ROS):
    """HxWx3 uint8 RGB -> sensor_msgs/CompressedImage as image_transport's compressed plugin publishes it.

    codec 'jpeg' (jpeg_quality 1-100) or 'png' (png_level 0-9); `encoding`: the encoding the camera's raw image
    had (written into the format, ``'<encoding>; <codec> compressed <target>'``): mono8 compresses a grey image
    (target mono8), every colour encoding BGR pixels (target bgr8), as the plugin does.
    """
    import cv2
    codec = _ALIASES.get(str(codec).lower())
    if codec is None:
        raise ValueError(f"codec must be one of {', '.join(CODECS)}, got {codec!r}")
    if not 1 <= int(jpeg_quality) <= 100:
        raise ValueError(f'jpeg_quality must be in [1, 100], got {jpeg_quality}')
    rgb = np.asarray(rgb_hw3)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f'expected HxWx3 uint8 RGB, got {rgb.dtype} {rgb.shape}')
    enc = encoding.lower()
    if enc == 'mono8':
        px, target = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), 'mono8'
    else:
        px, target = np.ascontiguousarray(rgb[:, :, ::-1]), 'bgr8'
    params = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)] if codec == 'jpeg' else \
        [cv2.IMWRITE_PNG_COMPRESSION, int(png_level)]
    ok, buf = cv2.imencode('.jpg' if codec == 'jpeg' else '.png', px, params)
    if not ok:
        raise ValueError(f'{codec.upper()} encoding failed')
    return types('sensor_msgs/msg/CompressedImage', header=header_for(header, frame_id, types),
                 format=f'{enc}; {codec} compressed {target}', data=types.u8(buf.tobytes()))
