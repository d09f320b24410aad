"""ROS message <-> numpy conversion for the node and the bag tools (no node logic, no rclpy import).

Decoders read fields only, so they accept both rclpy messages (sensor_msgs.msg.Image, ...) and the `rosbags`
library's message classes. Builders construct messages through a `MessageTypes` flavour: `ROS` (the generated
rclpy message classes, the default) or one made from a rosbags typestore (see data/rosbag_io.py), so the node
and the bag writer produce byte-identical content from the same code.

Conventions: stamps travel as integer nanoseconds (`stamp_to_ns`, `ns_to_stamp`); a header given to a builder is
copied field by field (stamp sec/nanosec and frame_id exactly). Depth inside the code is float32 metres with NaN
for "no estimate"; REP 118 encodings at the boundary: 32FC1 metres (NaN = none) or 16UC1 millimetres (0 = none).
Poses, transforms and odometry are in ``pose_msgs`` (quaternions (x, y, z, w) as in ROS), point clouds in
``cloud_msgs``, compressedDepth in ``compressed_depth``.
"""
from __future__ import annotations

import array
import importlib
from typing import Any, Callable

import numpy as np

from dpv_sensor.core.pose_math import scale_intrinsics_np

NS = 1_000_000_000

COLOUR_ENCODINGS = ('rgb8', 'bgr8', 'rgba8', 'bgra8', 'mono8')
# channels per pixel, and which source channels give R, G, B
_COLOUR = {'rgb8': (3, (0, 1, 2)), 'bgr8': (3, (2, 1, 0)), 'rgba8': (4, (0, 1, 2)),
           'bgra8': (4, (2, 1, 0)), 'mono8': (1, (0, 0, 0))}
# encodings that are valid ROS images but not colour: named in the error so the user sees what went wrong
_NOT_COLOUR = {'16uc1': 'a 16-bit depth/mono image', 'mono16': 'a 16-bit mono image', '32fc1': 'a float depth image',
               '8uc1': 'a single-channel 8UC1 image (use mono8 for grey)', 'yuv422': 'a YUV image',
               'uyvy': 'a YUV image', 'yuyv': 'a YUV image', 'rgb16': 'a 16-bit colour image',
               'bgr16': 'a 16-bit colour image', 'bayer_rggb8': 'a raw Bayer image (debayer first)',
               'bayer_bggr8': 'a raw Bayer image (debayer first)', 'bayer_gbrg8': 'a raw Bayer image (debayer first)',
               'bayer_grbg8': 'a raw Bayer image (debayer first)'}
DEPTH_ENCODINGS = ('32FC1', '16UC1')


# --------------------------------------------------------------------------------------------------------------
# errors
# --------------------------------------------------------------------------------------------------------------
class MessageError(ValueError):
    """A message the node cannot use; the text says exactly why."""


class UnsupportedEncoding(MessageError):
    """An image encoding the node does not read (e.g. 16UC1 sent on the colour topic)."""


class BadImage(MessageError):
    """An image whose fields disagree (data length vs step*height, step too small, zero size)."""


class BadCameraInfo(MessageError):
    """CameraInfo with an unusable K (all zeros, fx/fy <= 0, non-finite)."""


class BadOdometry(MessageError):
    """Odometry with NaN/inf values or a non-unit quaternion."""


class BadTransform(MessageError):
    """A TF transform with NaN / inf or a quaternion that is not unit length."""


# --------------------------------------------------------------------------------------------------------------
# message flavours
# --------------------------------------------------------------------------------------------------------------
class MessageTypes:
    """How to build messages of one flavour.

    get_class('sensor_msgs/msg/Image') -> class; u8(bytes) -> a value for a uint8[] field; f64seq(values) ->
    a value for an unbounded float64[] field. Builders always pass every field, so flavours whose classes have
    no defaults (rosbags) work too.
    """

    def __init__(self, name: str, get_class: Callable[[str], type], u8: Callable[[bytes], Any],
                 f64seq: Callable[[Any], Any]):
        self.name = name
        self._get_class = get_class
        self._cache: dict[str, type] = {}
        self.u8 = u8
        self.f64seq = f64seq

    def cls(self, typename: str) -> type:
        c = self._cache.get(typename)
        if c is None:
            c = self._cache[typename] = self._get_class(typename)
        return c

    def __call__(self, typename: str, **fields):
        return self.cls(typename)(**fields)


def ros_message_class(typename: str) -> type:
    """'sensor_msgs/msg/Image' (or 'sensor_msgs/Image') -> the generated rclpy message class."""
    parts = typename.split('/')
    if len(parts) == 2:
        parts = [parts[0], 'msg', parts[1]]
    if len(parts) != 3:
        raise ValueError(f'not a ROS message type name: {typename!r}')
    return getattr(importlib.import_module(f'{parts[0]}.{parts[1]}'), parts[2])


def _ros_u8(buf) -> array.array:
    out = array.array('B')
    out.frombytes(bytes(buf) if not isinstance(buf, (bytes, bytearray)) else buf)
    return out


ROS = MessageTypes('rclpy', ros_message_class, _ros_u8, lambda v: [float(x) for x in v])


def f64_values(values, n=None) -> np.ndarray:
    out = np.asarray(values, dtype=np.float64).reshape(-1)
    if n is not None and out.size != n:
        raise ValueError(f'expected {n} values, got {out.size}')
    return out


# --------------------------------------------------------------------------------------------------------------
# stamps and headers
# --------------------------------------------------------------------------------------------------------------
def stamp_to_ns(stamp) -> int:
    """builtin_interfaces/Time -> integer nanoseconds."""
    return int(stamp.sec) * NS + int(stamp.nanosec)


def ns_to_stamp(ns: int, types: MessageTypes = ROS):
    """Integer nanoseconds -> builtin_interfaces/Time (sec may be negative; nanosec in [0, 1e9))."""
    ns = int(ns)
    sec, nanosec = divmod(ns, NS)
    if not -2 ** 31 <= sec < 2 ** 31:
        raise ValueError(f'stamp {ns} ns does not fit builtin_interfaces/Time')
    return types('builtin_interfaces/msg/Time', sec=sec, nanosec=nanosec)


def stamp_to_sec(stamp) -> float:
    return stamp_to_ns(stamp) / NS


def make_header(stamp_ns: int, frame_id: str, types: MessageTypes = ROS):
    return types('std_msgs/msg/Header', stamp=ns_to_stamp(stamp_ns, types), frame_id=str(frame_id))


def copy_header(header, types: MessageTypes = ROS):
    """A header of `types`' flavour with exactly the stamp and frame_id of `header` (any flavour)."""
    return types('std_msgs/msg/Header',
                 stamp=types('builtin_interfaces/msg/Time', sec=int(header.stamp.sec),
                             nanosec=int(header.stamp.nanosec)),
                 frame_id=str(header.frame_id))


def header_for(header_or_stamp, frame_id, types: MessageTypes = ROS):
    """A header for an outgoing message: from a stamp in ns and ``frame_id``, or a copy of a received header."""
    if isinstance(header_or_stamp, (int, np.integer)):
        return make_header(int(header_or_stamp), frame_id or '', types)
    return copy_header(header_or_stamp, types)


# --------------------------------------------------------------------------------------------------------------
# images
# --------------------------------------------------------------------------------------------------------------
def _image_array(msg, bytes_per_pixel: int, what: str) -> np.ndarray:
    """The pixel bytes of `msg` as an HxWx(bytes_per_pixel) uint8 view, honouring `step` padding."""
    h, w, step = check_image_layout(msg, bytes_per_pixel, what)
    data = np.frombuffer(msg.data, dtype=np.uint8)
    return data.reshape(h, step)[:, :w * bytes_per_pixel].reshape(h, w, bytes_per_pixel)


def check_image_layout(msg, bytes_per_pixel: int, what: str) -> tuple[int, int, int]:
    """(height, width, step) of an image message whose size, step and data length agree (the one home of this
    check: on receipt and before the pixels are read). Raises BadImage naming `what` otherwise: zero size, a step
    shorter than a row of pixels, or data whose length is not exactly step*height (not a byte short or over)."""
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h <= 0 or w <= 0:
        raise BadImage(f'{what} has zero size ({w}x{h})')
    if step < w * bytes_per_pixel:
        raise BadImage(f'{what} step {step} is smaller than width*bytes per pixel = {w}*{bytes_per_pixel}')
    if len(msg.data) != step * h:
        raise BadImage(f'{what} data length {len(msg.data)} does not match step*height = {step}*{h} = {step * h}')
    return h, w, step


def check_colour_image(msg) -> tuple[int, tuple]:
    """(channels, channel order) of a colour sensor_msgs/Image whose encoding, size, step and data length agree,
    without touching the pixels (cheap enough for the subscription callback). Raises UnsupportedEncoding for an
    encoding other than rgb8, bgr8, rgba8, bgra8, mono8 and BadImage when size, step and data disagree."""
    enc = str(msg.encoding).strip().lower()
    if enc not in _COLOUR:
        what = _NOT_COLOUR.get(enc)
        hint = f' ({what})' if what else ''
        raise UnsupportedEncoding(f"unsupported image encoding '{msg.encoding}'{hint}; the colour input must be one "
                                  f"of {', '.join(COLOUR_ENCODINGS)}")
    channels, order = _COLOUR[enc]
    check_image_layout(msg, channels, f"'{msg.encoding}' image")
    return channels, order


def image_to_rgb(msg) -> np.ndarray:
    """sensor_msgs/Image (rgb8, bgr8, rgba8, bgra8, mono8) -> HxWx3 uint8 RGB (a new, contiguous array).

    Raises UnsupportedEncoding for any other encoding and BadImage when size, step and data disagree.
    """
    channels, order = check_colour_image(msg)
    px = _image_array(msg, channels, f"'{msg.encoding}' image")
    if channels == 1:
        return np.repeat(px, 3, axis=2)
    return np.ascontiguousarray(px[:, :, list(order)])


def rgb_to_image(rgb_hw3, header, frame_id: str | None = None, encoding: str = 'rgb8',
                 types: MessageTypes = ROS):
    """HxWx3 uint8 RGB -> sensor_msgs/Image in rgb8 / bgr8 / rgba8 / bgra8 / mono8 (tightly packed).

    `header` is a header to copy or an int stamp in ns (then `frame_id` names the frame).
    """
    rgb = np.asarray(rgb_hw3)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f'expected HxWx3 uint8 RGB, got {rgb.dtype} {rgb.shape}')
    enc = encoding.lower()
    if enc == 'rgb8':
        px = rgb
    elif enc == 'bgr8':
        px = rgb[:, :, ::-1]
    elif enc in ('rgba8', 'bgra8'):
        alpha = np.full(rgb.shape[:2] + (1,), 255, np.uint8)
        px = np.concatenate([rgb if enc == 'rgba8' else rgb[:, :, ::-1], alpha], axis=2)
    elif enc == 'mono8':
        grey = (0.299 * rgb[..., 0] + 0.587 * rgb[..., 1] + 0.114 * rgb[..., 2]).round()
        px = grey.astype(np.uint8)[:, :, None]
    else:
        raise UnsupportedEncoding(f"cannot write colour as '{encoding}'")
    px = np.ascontiguousarray(px)
    h, w, c = px.shape
    return types('sensor_msgs/msg/Image', header=header_for(header, frame_id, types), height=h, width=w,
                 encoding=enc, is_bigendian=0, step=w * c, data=types.u8(px.tobytes()))


def depth_to_mm(depth_hw) -> np.ndarray:
    """float metres (NaN / inf / <= 0 = no estimate) -> uint16 millimetres, rounded, 0 = none, clipped to 65535."""
    depth = np.asarray(depth_hw, dtype=np.float32)
    invalid = ~np.isfinite(depth) | (depth <= 0.0)
    mm = np.clip(np.round(np.where(invalid, 0.0, depth.astype(np.float64) * 1000.0)), 0, 65535)
    return mm.astype('<u2')


def depth_to_image(depth_hw, header, frame_id: str | None = None, encoding: str = '32FC1',
                   types: MessageTypes = ROS):
    """float depth in metres (NaN / inf / <= 0 = no estimate) -> sensor_msgs/Image.

    32FC1: metres, NaN for no estimate. 16UC1: millimetres rounded, 0 for no estimate, clipped to 65535.
    """
    depth = np.asarray(depth_hw, dtype=np.float32)
    if depth.ndim != 2:
        raise ValueError(f'depth must be HxW, got shape {depth.shape}')
    h, w = depth.shape
    invalid = ~np.isfinite(depth) | (depth <= 0.0)
    if encoding == '32FC1':
        px = np.where(invalid, np.float32(np.nan), depth).astype('<f4')
        bpp = 4
    elif encoding == '16UC1':
        px = depth_to_mm(depth)
        bpp = 2
    else:
        raise UnsupportedEncoding(f"depth encoding must be one of {', '.join(DEPTH_ENCODINGS)}, got '{encoding}'")
    return types('sensor_msgs/msg/Image', header=header_for(header, frame_id, types), height=h, width=w,
                 encoding=encoding, is_bigendian=0, step=w * bpp, data=types.u8(px.tobytes()))


def confidence_to_image(confidence_hw, header, frame_id: str | None = None, types: MessageTypes = ROS):
    """Confidence in [0, 1] -> 32FC1 image (NaN becomes 0: no estimate means no confidence)."""
    conf = np.nan_to_num(np.asarray(confidence_hw, dtype=np.float32), nan=0.0, posinf=1.0, neginf=0.0)
    conf = np.clip(conf, 0.0, 1.0).astype('<f4')
    h, w = conf.shape
    return types('sensor_msgs/msg/Image', header=header_for(header, frame_id, types), height=h, width=w,
                 encoding='32FC1', is_bigendian=0, step=w * 4, data=types.u8(conf.tobytes()))


def image_to_float(msg) -> np.ndarray:
    """32FC1 (as is) or 16UC1 (millimetres -> metres, 0 -> NaN) image -> HxW float32. Honours is_bigendian."""
    enc = str(msg.encoding).strip().upper()
    big = bool(msg.is_bigendian)
    if enc == '32FC1':
        px = _image_array(msg, 4, "'32FC1' image")
        return px.copy().view('>f4' if big else '<f4')[:, :, 0].astype(np.float32)
    if enc in ('16UC1', 'MONO16'):
        px = _image_array(msg, 2, f"'{msg.encoding}' image")
        mm = px.copy().view('>u2' if big else '<u2')[:, :, 0].astype(np.float32)
        return np.where(mm == 0, np.float32(np.nan), mm / np.float32(1000.0)).astype(np.float32)
    raise UnsupportedEncoding(f"expected a 32FC1 or 16UC1 image, got '{msg.encoding}'")


# --------------------------------------------------------------------------------------------------------------
# camera info
# --------------------------------------------------------------------------------------------------------------
def camera_info_to_K(msg) -> tuple[np.ndarray, tuple[int, int]]:
    """sensor_msgs/CameraInfo -> (K 3x3 float64, (width, height)). Raises BadCameraInfo for an unusable K."""
    k = np.asarray(msg.k, dtype=np.float64).reshape(-1)
    if k.size != 9:
        raise BadCameraInfo(f'camera_info K has {k.size} entries, expected 9')
    if not np.all(np.isfinite(k)):
        raise BadCameraInfo(f'camera_info K has non-finite entries: {k.tolist()}')
    if not np.any(k):
        raise BadCameraInfo('camera_info K is all zeros (uncalibrated camera?)')
    K = k.reshape(3, 3)
    if K[0, 0] <= 0.0 or K[1, 1] <= 0.0:
        raise BadCameraInfo(f'camera_info K has fx={K[0, 0]:g}, fy={K[1, 1]:g}; both must be > 0')
    if K[2, 2] == 0.0:
        raise BadCameraInfo('camera_info K[2][2] is 0 (expected 1)')
    return K / K[2, 2], (int(msg.width), int(msg.height))


def has_distortion(msg) -> bool:
    """True when the CameraInfo carries non-zero distortion coefficients (the node assumes rectified input)."""
    d = np.asarray(msg.d, dtype=np.float64).reshape(-1)
    return bool(d.size and np.any(np.abs(d) > 1e-12))


def scale_K(K_33, from_wh: tuple[int, int], to_wh: tuple[int, int]) -> np.ndarray:
    """Intrinsics of an image resized from `from_wh` to `to_wh` (pixel centres at integers:
    fx' = fx*sx, cx' = (cx + 0.5)*sx - 0.5, same for y)."""
    return scale_intrinsics_np(K_33, to_wh[0] / from_wh[0], to_wh[1] / from_wh[1])


def K_to_camera_info(K_33, width: int, height: int, header, frame_id: str | None = None,
                     types: MessageTypes = ROS):
    """A rectified pinhole CameraInfo: K, P = [K | 0], R = I, plumb_bob with zero distortion."""
    K = np.asarray(K_33, dtype=np.float64).reshape(3, 3)
    P = np.zeros((3, 4))
    P[:, :3] = K
    roi = types('sensor_msgs/msg/RegionOfInterest', x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return types('sensor_msgs/msg/CameraInfo', header=header_for(header, frame_id, types), height=int(height),
                 width=int(width), distortion_model='plumb_bob', d=types.f64seq([0.0] * 5), k=f64_values(K, 9),
                 r=f64_values(np.eye(3), 9), p=f64_values(P, 12), binning_x=0, binning_y=0, roi=roi)
