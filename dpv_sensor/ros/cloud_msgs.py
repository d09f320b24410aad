"""sensor_msgs/PointCloud2 <-> numpy: the XYZRGB cloud of a depth image (organised or only the valid points,
decimated for depth/points) and back (no rclpy import; message flavours as in ``msgs``)."""
from __future__ import annotations

import numpy as np

from dpv_sensor.ros.msgs import ROS, MessageError, MessageTypes, header_for

_FLOAT32 = 7  # sensor_msgs/PointField.FLOAT32


def pack_rgb(rgb_n3) -> np.ndarray:
    """uint8 RGB -> float32 whose bits are 0x00RRGGBB (the PCL / RViz 'rgb' field)."""
    rgb = np.asarray(rgb_n3, dtype=np.uint32)
    packed = (rgb[..., 0] << 16) | (rgb[..., 1] << 8) | rgb[..., 2]
    return packed.astype('<u4').view('<f4')


def unpack_rgb(rgb_f32) -> np.ndarray:
    """Inverse of pack_rgb: float32 packed colours -> uint8 RGB."""
    u = np.asarray(rgb_f32, dtype='<f4').view('<u4')
    return np.stack([(u >> 16) & 255, (u >> 8) & 255, u & 255], axis=-1).astype(np.uint8)


def depth_to_pointcloud(depth_hw, rgb_hw3, K_33, header, frame_id: str | None = None, skip_invalid: bool = False,
                        types: MessageTypes = ROS):
    """PointCloud2 XYZRGB (float32 x, y, z, packed rgb; point_step 16) in the camera (optical) frame.

    skip_invalid False (default): organised HxW cloud, pixels without depth are NaN points, is_dense False
    (what depth_image_proc publishes). True: only valid points, height 1, is_dense True.
    `rgb_hw3` must have the depth's size.
    """
    depth = np.asarray(depth_hw, dtype=np.float32)
    rgb = np.asarray(rgb_hw3, dtype=np.uint8)
    h, w = depth.shape
    if rgb.shape[:2] != (h, w):
        raise ValueError(f'colour {rgb.shape[:2]} and depth {(h, w)} sizes differ')
    K = np.asarray(K_33, dtype=np.float64)
    u = np.arange(w, dtype=np.float32)[None, :]
    v = np.arange(h, dtype=np.float32)[:, None]
    valid = np.isfinite(depth) & (depth > 0.0)
    z = np.where(valid, depth, np.float32(np.nan))
    x = (u - np.float32(K[0, 2])) / np.float32(K[0, 0]) * z
    y = (v - np.float32(K[1, 2])) / np.float32(K[1, 1]) * z
    pts = np.empty((h, w, 4), dtype='<f4')
    pts[..., 0], pts[..., 1], pts[..., 2] = x, y, z
    pts[..., 3] = pack_rgb(rgb)
    if skip_invalid:
        pts = pts[valid][None]
    ph, pw = pts.shape[:2]
    fields = [types('sensor_msgs/msg/PointField', name=n, offset=4 * i, datatype=_FLOAT32, count=1)
              for i, n in enumerate(('x', 'y', 'z', 'rgb'))]
    return types('sensor_msgs/msg/PointCloud2', header=header_for(header, frame_id, types), height=ph, width=pw,
                 fields=fields, is_bigendian=False, point_step=16, row_step=16 * pw,
                 data=types.u8(np.ascontiguousarray(pts).tobytes()), is_dense=bool(skip_invalid))


def pointcloud_to_xyzrgb(msg) -> tuple[np.ndarray, np.ndarray]:
    """PointCloud2 with float32 x, y, z and packed rgb -> (N x 3 float32 xyz, N x 3 uint8 rgb), NaNs kept."""
    offsets = {f.name: int(f.offset) for f in msg.fields}
    for name in ('x', 'y', 'z', 'rgb'):
        if name not in offsets:
            raise MessageError(f"point cloud has no '{name}' field (fields: {sorted(offsets)})")
    n = int(msg.width) * int(msg.height)
    raw = np.frombuffer(msg.data, dtype=np.uint8)
    step = int(msg.point_step)
    if raw.size < n * step:
        raise MessageError(f'point cloud data length {raw.size} < width*height*point_step = {n * step}')
    rows = raw[:n * step].reshape(n, step)
    end = '>' if msg.is_bigendian else '<'
    col = lambda name: rows[:, offsets[name]:offsets[name] + 4].copy().view(end + 'f4')[:, 0]  # noqa: E731
    xyz = np.stack([col('x'), col('y'), col('z')], axis=1).astype(np.float32)
    return xyz, unpack_rgb(col('rgb').astype('<f4'))



def decimate_for_cloud(depth_hw, rgb_hw3, K_33, decimation: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every ``decimation``-th pixel in each direction, starting at (0, 0), and the intrinsics of that grid.

    Pixel (i, j) of the result is pixel (i * n, j * n) of the input, so with K' = K with its first two rows divided
    by n it back-projects to exactly the same 3D point (u' = u / n: (u' - cx / n) / (fx / n) = (u - cx) / fx).
    """
    n = int(decimation)
    if n < 1:
        raise ValueError(f'decimation must be a positive integer, got {decimation!r}')
    K = np.array(K_33, dtype=np.float64).reshape(3, 3)
    K[:2] /= n
    return np.asarray(depth_hw)[::n, ::n], np.asarray(rgb_hw3)[::n, ::n], K


def depth_to_pointcloud_decimated(depth_hw, rgb_hw3, K_33, header, decimation: int = 1, frame_id: str | None = None,
                                  types: MessageTypes = ROS):
    """Organised XYZRGB PointCloud2 of every ``decimation``-th pixel (ceil(H/n) x ceil(W/n) points, NaN where no
    depth): ``depth_to_pointcloud`` on ``decimate_for_cloud``'s grid. decimation 1 is the full organised cloud;
    n shrinks the message n^2 times (640x480 at n = 4: 4.9 MB -> 0.31 MB)."""
    depth, rgb, K = decimate_for_cloud(depth_hw, rgb_hw3, K_33, decimation)
    return depth_to_pointcloud(depth, rgb, K, header, frame_id, skip_invalid=False, types=types)
