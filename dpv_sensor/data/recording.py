"""A user's own recording, read as the networks' adaptation needs it: colour images, intrinsics and camera poses,
**never depth** unless asked for (``depth_topic``: the adapt tool's ``--supervised`` on a bag).

:func:`load_recording` takes a sequence folder (images/ as PNG or JPEG, poses.txt, K.txt; its depth/ is never
looked at) or a rosbag2 (MCAP or sqlite3). In a bag the camera image (raw or image_transport compressed),
camera_info and odometry topics are found by message type as the demo and ``evaluate`` find them
(:mod:`dpv_sensor.data.topic_detection`); names are needed only to choose among several. Camera poses are the
odometry interpolated at each image stamp (SLERP + linear, :class:`dpv_sensor.stream.pose_buffer.PoseBuffer`, as the
node pairs them) composed with the camera mount: ``T_base_camera`` when given, else the bag's /tf_static from the
odometry's child frame to the image frame, else the identity (the odometry tracks the optical frame). Images
without a pose (before the first odometry sample, across a gap longer than ``max_odom_gap``) are dropped and
counted. With ``size`` the images are resized as they are read (K scaled with the project convention), so a long
recording is held in memory at the processing size only.

The result is a :class:`Recording`: a depth-free :class:`~dpv_sensor.data.sequence.Sequence` (asking it for depth
raises) and a ``source`` dict that says what was read. With ``depth_topic`` (a bag; a fleet where one robot carries
a depth camera) each image is paired with the depth image on that topic nearest its stamp within
``DEPTH_PAIRING_S``: a depth registered to the colour camera (same size, same intrinsics: a driver's
aligned_depth_to_color), 16UC1 millimetres or 32FC1 metres, resized by nearest neighbour; images without one are
dropped and counted.
"""
from __future__ import annotations

import dataclasses
import pathlib
from typing import Any, Dict, Optional, Tuple

import cv2
import numpy as np

from dpv_sensor import params as P
from dpv_sensor.core.pose_math import scale_intrinsics_np
from dpv_sensor.data.sequence import Sequence, SequenceFormatError, resize_nearest

__all__ = ['Recording', 'load_recording', 'is_bag', 'DEPTH_PAIRING_S']

#: an image and a depth image further apart than this (s) are not a pair (a 30 Hz depth camera that is not
#: synchronised with the colour camera is at most half a frame, 17 ms, from the nearest colour image)
DEPTH_PAIRING_S = 0.02


@dataclasses.dataclass
class Recording:
    """A depth-free sequence and what it was read from (``source``: kind, path, frames, topics, dropped images)."""
    sequence: Sequence
    source: Dict[str, Any]

    @property
    def name(self) -> str:
        return str(self.source.get('name', self.sequence.name))


def is_bag(path) -> bool:
    """A rosbag2: a folder with metadata.yaml, or an .mcap / .db3 file."""
    p = pathlib.Path(path)
    return (p.is_dir() and (p / 'metadata.yaml').is_file()) or (p.is_file() and p.suffix in ('.mcap', '.db3'))


def load_recording(path, *, size: Optional[Tuple[int, int]] = None, image_topic: Optional[str] = None,
                   camera_info_topic: Optional[str] = None, odom_topic: Optional[str] = None, T_base_camera=None,
                   max_odom_gap: float = P.default('max_odom_gap'), depth_topic: Optional[str] = None) -> Recording:
    """Read a sequence folder or a rosbag2 (see the module docstring). ``size`` = (width, height) to resize to;
    ``depth_topic`` (bags only) the registered depth to pair with the images.

    Raises SequenceFormatError (a folder) or ``rosbag_io.BagError`` (a bag) naming what is wrong, FileNotFoundError
    when ``path`` is neither."""
    p = pathlib.Path(path)
    if not p.exists():
        raise FileNotFoundError(f'{p}: no such sequence folder or bag')
    if is_bag(p):
        return _load_bag(p, size, image_topic, camera_info_topic, odom_topic, T_base_camera, max_odom_gap,
                         depth_topic)
    if depth_topic:
        raise SequenceFormatError(f'{p}: a depth topic is read from a bag; a sequence folder has depth/')
    if not p.is_dir():
        raise SequenceFormatError(f'{p}: neither a sequence folder (images/, poses.txt, K.txt) nor a rosbag2')
    seq = Sequence(p, depth=False)
    if len(seq) == 0:
        raise SequenceFormatError(f'{p}: images/ holds no PNG or JPEG images')
    native = seq.size
    if size is not None:
        seq = seq.resized(*size)
    source = {'kind': 'folder', 'path': str(p.resolve()), 'name': p.name, 'frames': len(seq),
              'native_size': list(native), 'depth_read': False}
    return Recording(seq, source)


def _camera_mount(path, topics: dict, odom_frames: set, image_frame: str, T_base_camera) -> Tuple[np.ndarray, str]:
    """(T_base_camera, where it came from): given, /tf_static of the bag, or the identity."""
    from dpv_sensor.data import rosbag_io as R
    if T_base_camera is not None:
        return R.as_T_base_camera(T_base_camera), 'given'
    if topics.get(R.TF_STATIC_TOPIC, ('',))[0] == R.TF_MESSAGE and len(odom_frames) == 1:
        from dpv_sensor.ros.pose_msgs import transform_to_matrix
        from dpv_sensor.stream.transform_tree import TransformTree
        tree = TransformTree()
        for _t, _ty, _log, msg in R.read_messages(path, [R.TF_STATIC_TOPIC]):
            for tf in msg.transforms:
                tree.set(tf.header.frame_id, tf.child_frame_id, transform_to_matrix(tf.transform), static=True)
        base = next(iter(odom_frames))
        found = tree.lookup(base, image_frame)
        if found.ok:
            return found.T_target_source_44, f'/tf_static {base} -> {image_frame}'
        return np.eye(4), f'identity (/tf_static: {found.reason})'
    return np.eye(4), 'identity'


def _load_bag(path: pathlib.Path, size, image_topic, camera_info_topic, odom_topic, T_base_camera,
              max_odom_gap: float, depth_topic: Optional[str]) -> Recording:
    from dpv_sensor.data import rosbag_io as R
    from dpv_sensor.data.topic_detection import describe_choice, detect_input_topics
    from dpv_sensor.stream.pose_buffer import PoseBuffer
    topics = R.bag_topics(path)
    depths = _DepthPairs(path, depth_topic) if depth_topic else None
    if depth_topic:
        topics = {t: v for t, v in topics.items() if t != depth_topic}    # never taken for the colour image
    chosen, how = detect_input_topics(topics, image=image_topic, camera_info=camera_info_topic, odom=odom_topic,
                                      options={'image': '--image-topic', 'camera_info': '--camera-info-topic',
                                               'odom': '--odom-topic'})
    infos = R.read_camera_infos(path, chosen['camera_info'])
    if not infos:
        raise R.BagError(f'{path}: {chosen["camera_info"]} holds no camera_info message')
    K_native, info_size = infos[0].data, tuple(infos[0].extra['size'])
    odom = R.read_odometry(path, chosen['odom'])
    if not odom:
        raise R.BagError(f'{path}: {chosen["odom"]} holds no odometry message')
    images = R.read_images(path, chosen['image'])
    if not images:
        raise R.BagError(f'{path}: {chosen["image"]} holds no image')
    mount, mount_from = _camera_mount(path, topics, {s.extra['child_frame_id'] for s in odom}, images[0].frame_id,
                                      T_base_camera)
    buf = PoseBuffer(max_gap_s=max_odom_gap, history_s=1e9, T_base_camera_44=mount, backwards_tolerance_s=1e9)
    for s in odom:
        buf.add(s.stamp_ns, None if np.isnan(s.data).any() else s.data)
    h0, w0 = images[0].data.shape[:2]
    if (w0, h0) != info_size:
        raise R.BagError(f'{path}: images are {w0}x{h0} but camera_info says {info_size[0]}x{info_size[1]}')
    out_wh = (w0, h0) if size is None else (int(size[0]), int(size[1]))
    K = scale_intrinsics_np(K_native, out_wh[0] / w0, out_wh[1] / h0)
    kept, kept_depth, poses, stamps, dropped = [], [], [], [], {}
    for s in images:
        if s.data.shape[:2] != (h0, w0):
            dropped['size_changed'] = dropped.get('size_changed', 0) + 1
            continue
        q = buf.pose_at(s.stamp_ns)
        if not q.ok:
            key = f'no_pose ({q.reason})'
            dropped[key] = dropped.get(key, 0) + 1
            continue
        if depths is not None:
            d = depths.at(s.stamp_ns, (w0, h0))
            if d is None:
                dropped['no_depth'] = dropped.get('no_depth', 0) + 1
                continue
            kept_depth.append(d if out_wh == (w0, h0) else resize_nearest(d, *out_wh))
        im = s.data if out_wh == (w0, h0) else cv2.resize(s.data, out_wh, interpolation=cv2.INTER_AREA)
        kept.append(im)
        poses.append(q.T_world_cam_44)
        stamps.append(s.stamp_ns / R.NS)
    if not kept:
        raise R.BagError(f'{path}: no image of {chosen["image"]} has an odometry pose'
                         f'{" and a depth image" if depths else ""} ({dropped})')
    seq = Sequence.from_arrays(kept, kept_depth if depths else None, np.stack(poses), K, np.asarray(stamps),
                               name=path.stem)
    source = {'kind': 'bag', 'path': str(path.resolve()), 'name': path.stem, 'frames': len(seq),
              'native_size': [w0, h0], 'topics': chosen, 'topics_chosen': describe_choice(chosen, how),
              'camera_mount': mount_from, 'images_dropped': dropped, 'depth_read': depths is not None}
    if depths is not None:
        source['depth_topic'] = depth_topic
        source['depth_offset_ms_max'] = round(depths.worst_offset_s * 1e3, 3)
    return Recording(seq, source)


class _DepthPairs:
    """The depth images of a bag topic, looked up by the colour image's stamp (nearest within DEPTH_PAIRING_S)."""

    def __init__(self, path: pathlib.Path, topic: str):
        from dpv_sensor.data import rosbag_io as R
        self._depths = sorted(R.read_depth_images(path, topic), key=lambda s: s.stamp_ns)
        if not self._depths:
            raise R.BagError(f'{path}: {topic} holds no depth image')
        self._stamps = np.array([s.stamp_ns for s in self._depths], dtype=np.int64)
        self.topic = topic
        self.worst_offset_s = 0.0

    def at(self, stamp_ns: int, size_wh: Tuple[int, int]) -> Optional[np.ndarray]:
        """The depth (HxW float32 metres, NaN none) nearest ``stamp_ns`` within DEPTH_PAIRING_S, else None; a depth
        of another size than the colour image is an error (it is not registered to the colour camera)."""
        from dpv_sensor.data import rosbag_io as R
        j = int(np.searchsorted(self._stamps, stamp_ns))
        near = [k for k in (j - 1, j) if 0 <= k < len(self._stamps)]
        k = min(near, key=lambda k: abs(int(self._stamps[k]) - stamp_ns))
        offset_s = abs(int(self._stamps[k]) - stamp_ns) / R.NS
        if offset_s > DEPTH_PAIRING_S:
            return None
        d = self._depths[k].data
        if (d.shape[1], d.shape[0]) != tuple(size_wh):
            raise R.BagError(f'{self.topic}: depth images are {d.shape[1]}x{d.shape[0]} but the colour images '
                             f'{size_wh[0]}x{size_wh[1]}: record the depth registered to the colour camera (e.g. '
                             'aligned_depth_to_color)')
        self.worst_offset_s = max(self.worst_offset_s, offset_s)
        return d
