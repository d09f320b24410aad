"""compressedDepth (image_transport's compressed_depth_image_transport, PNG) <-> numpy: the node's
depth/image/compressedDepth and its decoder (no rclpy import; message flavours as in ``msgs``)."""
from __future__ import annotations

import struct

import numpy as np

from dpv_sensor.ros.msgs import (DEPTH_ENCODINGS, ROS, BadImage, MessageTypes, UnsupportedEncoding, depth_to_mm,
                                 header_for)

#: The 12-byte header in front of the PNG: int32 compression format (0 = INV_DEPTH, written for every image),
#: float32 depthParam[2] (the inverse-depth quantisation a, b; zero for 16UC1). Little-endian, as the plugin's
#: memcpy of its struct on the platforms ROS 2 supports.
COMPRESSED_DEPTH_HEADER = struct.Struct('<iff')
COMPRESSED_DEPTH_INV_DEPTH = 0
#: The plugin's parameter defaults (png_level, depth_max m, depth_quantization).
COMPRESSED_DEPTH_DEFAULTS = {'png_level': 9, 'depth_max': 10.0, 'depth_quantization': 100.0}


def compressed_depth_quantisation(depth_max: float, depth_quantization: float) -> tuple[np.float32, np.float32]:
    """(a, b) of the 32FC1 inverse-depth code q = a / d + b, in float32 as the plugin computes them:
    a = z0 * (z0 + 1), b = 1 - a / depth_max (z0 = depth_quantization). Defaults: a = 10100, b = -1009."""
    z0 = np.float32(depth_quantization)
    a = np.float32(z0 * (z0 + np.float32(1.0)))
    b = np.float32(np.float32(1.0) - a / np.float32(depth_max))
    return a, b


def _png_u16(px_hw: np.ndarray, png_level: int) -> bytes:
    import cv2
    ok, buf = cv2.imencode('.png', np.ascontiguousarray(px_hw, dtype=np.uint16),
                           [cv2.IMWRITE_PNG_COMPRESSION, int(png_level)])
    if not ok:
        raise BadImage('PNG encoding of the depth image failed')
    return buf.tobytes()


def depth_to_compressed_depth(depth_hw, header, frame_id: str | None = None, encoding: str = '16UC1',
                              depth_max: float = 10.0, depth_quantization: float = 100.0, png_level: int = 9,
                              types: MessageTypes = ROS):
    """float depth in metres (NaN / inf / <= 0 = no estimate) -> sensor_msgs/CompressedImage as image_transport's
    compressedDepth plugin publishes it (topic ``<image topic>/compressedDepth``), PNG flavour.

    format ``'<encoding>; compressedDepth png'``; data = 12-byte ``COMPRESSED_DEPTH_HEADER`` + a 16-bit PNG:
    - 16UC1: the image's millimetres (``depth_to_mm``), those above int(depth_max * 1000) set to 0; header
      (INV_DEPTH, 0, 0).
    - 32FC1: q = trunc(a / d + b) as uint16 (``compressed_depth_quantisation``), 0 for no estimate and for
      d >= depth_max; header (INV_DEPTH, a, b). Depth resolution falls with distance (defaults: 0.1 mm at 1 m,
      1 cm at 10 m). Depths closer than a / (65535 - b) (0.152 m by default) overflow the 16 bits in the plugin
      (undefined in C++); here they saturate to code 65535, i.e. decode to that closest depth.
    """
    depth = np.asarray(depth_hw, dtype=np.float32)
    if depth.ndim != 2:
        raise ValueError(f'depth must be HxW, got shape {depth.shape}')
    if not depth_max > 0 or not depth_quantization > 0:
        raise ValueError('depth_max and depth_quantization must be positive')
    if encoding == '16UC1':
        px = depth_to_mm(depth)
        px[px > int(depth_max * 1000.0)] = 0
        head = COMPRESSED_DEPTH_HEADER.pack(COMPRESSED_DEPTH_INV_DEPTH, 0.0, 0.0)
    elif encoding == '32FC1':
        a, b = compressed_depth_quantisation(depth_max, depth_quantization)
        keep = np.isfinite(depth) & (depth > 0.0) & (depth < np.float32(depth_max))
        with np.errstate(divide='ignore', invalid='ignore'):
            q = np.where(keep, a / depth + b, np.float32(0.0)).astype(np.float32)
        px = np.trunc(np.clip(q, 0.0, 65535.0)).astype(np.uint16)
        head = COMPRESSED_DEPTH_HEADER.pack(COMPRESSED_DEPTH_INV_DEPTH, float(a), float(b))
    else:
        raise UnsupportedEncoding(f"compressedDepth encodes {', '.join(DEPTH_ENCODINGS)}, got '{encoding}'")
    return types('sensor_msgs/msg/CompressedImage', header=header_for(header, frame_id, types),
                 format=f'{encoding}; compressedDepth png', data=types.u8(head + _png_u16(px, png_level)))


def compressed_depth_to_float(msg) -> np.ndarray:
    """A compressedDepth (PNG) sensor_msgs/CompressedImage -> HxW float32 metres, NaN = no estimate.

    Reads what ``depth_to_compressed_depth`` and image_transport's plugin write: 16UC1 millimetres (0 = none) or
    32FC1 inverse-depth codes (d = a / (q - b) with a, b from the header; q = 0 = none). A format without
    ``';'`` is the plugin's older PNG-only form; 'compressedDepth rvl' is not supported.
    """
    import cv2
    fmt = str(msg.format)
    encoding, _, rest = fmt.partition(';')
    encoding = encoding.strip()
    rest = rest.strip()
    if rest and rest not in ('compressedDepth', 'compressedDepth png'):
        raise UnsupportedEncoding(f"only PNG compressedDepth is supported, got format '{fmt}'")
    if encoding.upper() not in DEPTH_ENCODINGS:
        raise UnsupportedEncoding(f"compressedDepth image of encoding '{encoding}' (expected 32FC1 or 16UC1)")
    data = bytes(msg.data)
    n = COMPRESSED_DEPTH_HEADER.size
    if len(data) <= n:
        raise BadImage(f'compressedDepth data of {len(data)} bytes holds no image after its {n}-byte header')
    _fmt_id, a, b = COMPRESSED_DEPTH_HEADER.unpack_from(data)
    px = cv2.imdecode(np.frombuffer(data[n:], np.uint8), cv2.IMREAD_UNCHANGED)
    if px is None or px.dtype != np.uint16 or px.ndim != 2:
        raise BadImage('compressedDepth payload is not a single-channel 16-bit PNG')
    if encoding.upper() == '16UC1':
        return np.where(px == 0, np.float32(np.nan), px / np.float32(1000.0)).astype(np.float32)
    q = px.astype(np.float32)
    with np.errstate(divide='ignore'):
        return np.where(px == 0, np.float32(np.nan), np.float32(a) / (q - np.float32(b))).astype(np.float32)
