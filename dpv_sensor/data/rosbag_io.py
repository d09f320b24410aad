"""rosbag2 read / write for dpv_sensor with the `rosbags` library (no rclpy; ROS 2 Jazzy message definitions).

- `write_sequence_bag`: a posed image sequence (a `Sequence`, the synthetic renderer's output, or plain arrays via
  `ArraySequence`) -> a bag with sensor_msgs/Image on /image (or, with ``compressed``, image_transport's
  sensor_msgs/CompressedImage JPEG or PNG on /image/compressed), sensor_msgs/CameraInfo on /camera_info
  and nav_msgs/Odometry on /odom, odometry at its own rate (interpolated between frames), with optional noise and
  dropouts, and optionally the camera mount on /tf_static (tf2_msgs/TFMessage, latched as robot_state_publisher
  publishes it). MCAP by default, sqlite3 on request.
- `BagWriter`: a generic writer (rosbags messages or raw CDR bytes) — what `bag record` uses for a live graph.
- Readers: `bag_topics`, `read_messages`, `read_images`, `read_depth_images`, `read_camera_infos`,
  `read_odometry` return numpy arrays with the exact header stamps (ns) and frame ids.

Which bag topic is the camera image, camera_info, odometry (by message type) is `dpv_sensor.data.topic_detection`;
a recorded depth bag exported to files is `dpv_sensor.data.bag_export`.

Messages are built with the same code as the node's (dpv_sensor.ros.msgs) in the `rosbags` flavour (`ROSBAGS`).
"""
from __future__ import annotations

import functools
import os
import pathlib
from dataclasses import dataclass, field
from typing import Any, Iterable, Iterator

import numpy as np

from dpv_sensor.ros import msgs as M
from dpv_sensor.ros import pose_msgs as PM
from dpv_sensor.ros.tf_publisher import tf_message, transform_stamped
from dpv_sensor.stream.pose_buffer import interpolate_pose, make_pose, pose7_to_matrix

NS = 1_000_000_000

IMAGE_TOPIC = '/image'
CAMERA_INFO_TOPIC = '/camera_info'
ODOM_TOPIC = '/odom'
DEPTH_TOPIC = '/depth/image'
CONFIDENCE_TOPIC = '/confidence/image'
DEPTH_INFO_TOPIC = '/depth/camera_info'

IMAGE = 'sensor_msgs/msg/Image'
COMPRESSED_IMAGE = 'sensor_msgs/msg/CompressedImage'
COMPRESSED_SUFFIX = '/compressed'         # image_transport's compressed topic: the image topic's child
CAMERA_INFO = 'sensor_msgs/msg/CameraInfo'
ODOMETRY = 'nav_msgs/msg/Odometry'
POSE_STAMPED = 'geometry_msgs/msg/PoseStamped'
TF_MESSAGE = 'tf2_msgs/msg/TFMessage'
TF_STATIC_TOPIC = '/tf_static'
TF_TOPIC = '/tf'

STORAGES = ('mcap', 'sqlite3')

_TYPESTORE = None


class BagError(RuntimeError):
    """A bag that cannot be written or read as asked (exists, missing topic, wrong type)."""


def typestore():
    """The rosbags typestore with the ROS 2 Jazzy message definitions (created once)."""
    global _TYPESTORE
    if _TYPESTORE is None:
        from rosbags.typesys import Stores, get_typestore
        _TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
    return _TYPESTORE


def _rosbags_class(typename: str):
    try:
        return typestore().types[typename]
    except KeyError:
        raise BagError(f'message type {typename!r} is not in the ROS 2 Jazzy typestore') from None


# dpv_sensor.ros.msgs builders in the rosbags flavour
ROSBAGS = M.MessageTypes('rosbags', _rosbags_class, lambda b: np.frombuffer(bytes(b), dtype=np.uint8),
                         lambda v: np.asarray(list(v), dtype=np.float64))


def qos_profile(reliable: bool = True, depth: int = 10, latched: bool = False):
    """A rosbags Qos record (keep-last, volatile; transient local when `latched`, as /tf_static) for a
    connection's offered_qos_profiles."""
    from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime)
    zero = QosTime(sec=0, nsec=0)
    return Qos(history=QosHistory.KEEP_LAST, depth=int(depth),
               reliability=QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT,
               durability=QosDurability.TRANSIENT_LOCAL if latched else QosDurability.VOLATILE,
               deadline=zero, lifespan=zero,
               liveliness=QosLiveliness.AUTOMATIC, liveliness_lease_duration=zero,
               avoid_ros_namespace_conventions=False)


# --------------------------------------------------------------------------------------------------------------
# writing
# --------------------------------------------------------------------------------------------------------------
class BagWriter:
    """Generic rosbag2 writer: `write(topic, msgtype, msg_or_cdr, stamp_ns)`; connections made on first use.

    `msg_or_cdr` is a rosbags message (serialised here) or the CDR bytes of a message (as a live subscription
    with raw=True delivers them). Usable as a context manager; safe to call from one thread at a time.
    """

    def __init__(self, path: str | os.PathLike, storage: str = 'mcap', overwrite: bool = False):
        from rosbags.rosbag2 import StoragePlugin, Writer
        if storage not in STORAGES:
            raise BagError(f'storage must be one of {STORAGES}, got {storage!r}')
        self.path = pathlib.Path(path)
        if self.path.exists():
            if not overwrite:
                raise BagError(f'{self.path} exists already (pass overwrite=True / --overwrite to replace it)')
            import shutil
            shutil.rmtree(self.path)
        plugin = StoragePlugin.MCAP if storage == 'mcap' else StoragePlugin.SQLITE3
        self._writer = Writer(self.path, version=9, storage_plugin=plugin)
        self._writer.open()
        self._connections: dict[tuple[str, str], Any] = {}
        self.counts: dict[str, int] = {}
        self.closed = False

    def connection(self, topic: str, msgtype: str, qos=None):
        key = (topic, msgtype)
        conn = self._connections.get(key)
        if conn is None:
            _rosbags_class(msgtype)  # a clear error for unknown types
            conn = self._writer.add_connection(topic, msgtype, typestore=typestore(),
                                               offered_qos_profiles=[qos or qos_profile()])
            self._connections[key] = conn
            self.counts[topic] = 0
        return conn

    def write(self, topic: str, msgtype: str, msg, stamp_ns: int, qos=None) -> None:
        conn = self.connection(topic, msgtype, qos)
        if isinstance(msg, (bytes, bytearray, memoryview)):
            data = bytes(msg)
        else:
            data = typestore().serialize_cdr(msg, msgtype)
        self._writer.write(conn, int(stamp_ns), data)
        self.counts[topic] += 1

    def close(self) -> None:
        if not self.closed:
            self._writer.close()
            self.closed = True

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class ArraySequence:
    """Plain arrays in the sequence interface (len, K, size, image(i), pose(i), stamp(i), depth(i))."""

    def __init__(self, images, poses, K, stamps=None, depths=None, rate: float = 30.0):
        self._images = images
        self._poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
        self.K = np.asarray(K, dtype=np.float64).reshape(3, 3)
        self._stamps = (np.arange(len(self._poses)) / rate) if stamps is None else np.asarray(stamps, np.float64)
        self._depths = depths
        h, w = np.asarray(images[0]).shape[:2]
        self.size = (int(w), int(h))
        if not len(images) == len(self._poses) == len(self._stamps):
            raise ValueError(f'{len(images)} images, {len(self._poses)} poses, {len(self._stamps)} stamps')

    def __len__(self):
        return len(self._poses)

    def image(self, i):
        return np.asarray(self._images[i])

    @property
    def has_depth(self) -> bool:
        return self._depths is not None

    def depth(self, i):
        if self._depths is None:
            raise ValueError('this sequence has no depth')
        return np.asarray(self._depths[i])

    def pose(self, i):
        return self._poses[i].copy()

    def stamp(self, i):
        return float(self._stamps[i])


@dataclass
class BagSummary:
    path: pathlib.Path
    storage: str
    frames: int
    odometry: int
    odometry_dropped: int
    start_ns: int
    end_ns: int
    image_stamps_ns: list[int] = field(default_factory=list)
    image_topic: str = IMAGE_TOPIC
    image_format: str = ''           # CompressedImage's format field ('' for raw images)

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) / NS


def as_T_base_camera(T_base_camera) -> np.ndarray:
    """The camera mount as a 4x4 T_base_camera: identity for None, a 4x4 as is, [x,y,z,qx,qy,qz,qw] made a matrix."""
    if T_base_camera is None:
        return np.eye(4)
    a = np.asarray(T_base_camera, dtype=np.float64)
    return a if a.shape == (4, 4) else pose7_to_matrix(a.reshape(-1))


def _perturb(T: np.ndarray, rng, pos_sigma: float, rot_sigma_rad: float) -> np.ndarray:
    """T with white Gaussian noise on the translation (m) and a small random rotation (rad, per axis)."""
    if pos_sigma <= 0 and rot_sigma_rad <= 0:
        return T
    out = T.copy()
    out[:3, 3] += rng.normal(0.0, pos_sigma, 3) if pos_sigma > 0 else 0.0
    if rot_sigma_rad > 0:
        w = rng.normal(0.0, rot_sigma_rad, 3)
        angle = float(np.linalg.norm(w))
        if angle > 0:
            axis = w / angle
            q = np.concatenate([axis * np.sin(angle / 2), [np.cos(angle / 2)]])
            out[:3, :3] = out[:3, :3] @ make_pose(np.zeros(3), q)[:3, :3]
    return out


COVARIANCE_FLOOR_SIGMA = 1e-6   # m and rad: the smallest sigma written with pose_variance


def _pose_variance(pose_variance, n_frames: int, idx: list[int], name: str = 'pose_variance') -> np.ndarray | None:
    """write_sequence_bag's pose_variance (or twist_variance: `name`) checked (one finite, non-negative row of two per
    frame) and taken at the written frames; None when not given."""
    if pose_variance is None:
        return None
    var = np.asarray(pose_variance, dtype=np.float64)
    if var.shape != (n_frames, 2):
        raise BagError(f'{name} must have one row (linear, angular variance) per frame: shape '
                       f'({n_frames}, 2), got {var.shape}')
    if not (np.all(np.isfinite(var)) and np.all(var >= 0)):
        raise BagError(f'{name} must be finite and non-negative')
    return var[idx]


def _sequence_pose_at(stamps_ns: np.ndarray, poses: np.ndarray, t_ns: int) -> np.ndarray:
    """Camera pose of the sequence at t (SLERP + linear between the two frames around it; clamped at the ends)."""
    i = int(np.searchsorted(stamps_ns, t_ns, side='left'))
    if i < len(stamps_ns) and stamps_ns[i] == t_ns:
        return poses[i]
    if i == 0:
        return poses[0]
    if i >= len(stamps_ns):
        return poses[-1]
    a = (t_ns - stamps_ns[i - 1]) / (stamps_ns[i] - stamps_ns[i - 1])
    return interpolate_pose(poses[i - 1], poses[i], a)


def odometry_stamps(image_stamps_ns: np.ndarray, odom_rate: float | None) -> np.ndarray:
    """Odometry times: the image stamps (odom_rate None/0) or a regular grid at odom_rate Hz from the first to the
    last image stamp (the last image stamp is always included so every image is bracketed)."""
    if not odom_rate:
        return np.asarray(image_stamps_ns, dtype=np.int64)
    t0, t1 = int(image_stamps_ns[0]), int(image_stamps_ns[-1])
    period = NS / float(odom_rate)
    n = int(np.floor((t1 - t0) / period + 1e-9))
    grid = t0 + np.round(np.arange(n + 1) * period).astype(np.int64)
    if grid[-1] < t1:
        grid = np.append(grid, t1)
    return grid


def _check_write_options(storage: str, idx: list, rate: float | None, odom_dropout: float) -> None:
    """BagError for options write_sequence_bag cannot write."""
    if storage not in STORAGES:
        raise BagError(f'storage must be one of {STORAGES}, got {storage!r}')
    if not idx:
        raise BagError('no frames to write')
    if rate is not None and rate <= 0:
        raise BagError(f'rate must be > 0, got {rate}')
    if not 0.0 <= odom_dropout < 1.0:
        raise BagError(f'odom_dropout must be in [0, 1), got {odom_dropout}')


def write_sequence_bag(path: str | os.PathLike, seq, *, storage: str = 'mcap', rate: float | None = None,
                       odom_rate: float | None = None, odom_noise: tuple[float, float] = (0.0, 0.0),
                       odom_dropout: float = 0.0, seed: int = 0, start_ns: int | None = None,
                       image_topic: str | None = None, camera_info_topic: str = CAMERA_INFO_TOPIC,
                       odom_topic: str = ODOM_TOPIC, camera_frame: str = 'camera_optical_frame',
                       odom_frame: str = 'odom', base_frame: str = 'base_link', T_base_camera=None,
                       encoding: str = 'rgb8', frames: Iterable[int] | None = None, with_odometry: bool = True,
                       pose_variance=None, twist_variance=None, compressed: str | None = None, jpeg_quality: int = 90,
                       tf_static: bool = False, camera_link: str = '', depth_topic: str | None = None,
                       overwrite: bool = False, progress: bool = True) -> BagSummary:
    """Write a posed image sequence as a rosbag2 and return what was written.

    seq: anything with len(), .K, image(i) (uint8 RGB), pose(i) (4x4 T_world_cam) and stamp(i) (s); e.g. a
    data.sequence.Sequence or an ArraySequence. rate: camera rate in Hz (stamps start_ns + i/rate); None keeps
    the sequence's own stamps (shifted to start at start_ns when given). odom_rate: odometry rate in Hz (None:
    one message per image, at its stamp). odom_noise: (position sigma m, rotation sigma deg) white noise per
    message. odom_dropout: probability that an odometry message is left out (the first and last never are).
    T_base_camera: camera pose in the odometry child frame ([x,y,z,qx,qy,qz,qw] or 4x4); odometry carries
    T_world_base = T_world_cam @ inv(T_base_camera). pose_variance: one row per sequence frame (position variance
    per axis m^2, rotation variance per axis rad^2), e.g. data.trajectory.corruption_variance: the odometry's pose
    covariance then carries it (linear in time between frames, plus the odom_noise variances) as an odometry that
    reports its own accumulated uncertainty does; None: only the odom_noise variances. twist_variance: one row per
    sequence frame (linear variance per axis m^2/s, angular variance per axis rad^2/s), e.g.
    data.trajectory.corruption_twist_variance: the odometry's twist covariance (linear in time between frames; zeros
    without it), as a wheel odometry publishes its motion noise. compressed: 'jpeg' or 'png'
    writes image_transport's sensor_msgs/CompressedImage (``ros.compressed_image.rgb_to_compressed``: format
    '<encoding>; jpeg compressed bgr8', JPEG at jpeg_quality) instead of sensor_msgs/Image, as a robot recording its
    camera's compressed topic; image_topic defaults to /image, or /image/compressed with `compressed`. The bag's
    record time of
    every message is its header stamp; at equal stamps odometry is written before camera_info, camera_info before
    the image. tf_static: also write the mount (T_base_camera) on /tf_static, one latched message before everything
    else: base_frame -> camera_frame, or with `camera_link` a chain of two as a URDF has it: base_frame -> camera_link
    (the mount's translation) -> camera_frame (its rotation). depth_topic: also write the sequence's depth there,
    16UC1 millimetres at each image's stamp in the camera frame (a depth camera registered to the colour camera,
    e.g. a driver's aligned_depth_to_color).
    """
    idx = list(range(len(seq))) if frames is None else [int(i) for i in frames]
    _check_write_options(storage, idx, rate, odom_dropout)
    image_writer, image_topic = _image_writer(compressed, jpeg_quality, encoding, image_topic)
    if rate is not None:
        base = 0 if start_ns is None else int(start_ns)
        img_ns = np.array([base + int(round(k * NS / rate)) for k in range(len(idx))], dtype=np.int64)
    else:
        raw = np.array([int(round(seq.stamp(i) * NS)) for i in idx], dtype=np.int64)
        img_ns = raw if start_ns is None else raw - raw[0] + int(start_ns)
    if np.any(np.diff(img_ns) <= 0):
        raise BagError('image stamps must increase strictly')
    T_bc = as_T_base_camera(T_base_camera)
    T_cb = np.linalg.inv(T_bc)
    poses = np.stack([np.asarray(seq.pose(i), dtype=np.float64) for i in idx])
    K = np.asarray(seq.K, dtype=np.float64)

    variance_n2 = _pose_variance(pose_variance, len(seq), idx)
    twist_n2 = _pose_variance(twist_variance, len(seq), idx, 'twist_variance')
    rng = np.random.default_rng(seed)
    events: list[tuple[int, int, str, Any]] = []   # (stamp, order, kind, payload)
    odom_count = odom_dropped = 0
    if with_odometry:
        o_ns = odometry_stamps(img_ns, odom_rate)
        pos_sigma, rot_sigma = float(odom_noise[0]), float(np.deg2rad(odom_noise[1]))
        for k, t in enumerate(o_ns):
            if odom_dropout and 0 < k < len(o_ns) - 1 and rng.random() < odom_dropout:
                odom_dropped += 1
                continue
            T_wb = _sequence_pose_at(img_ns, poses, int(t)) @ T_cb
            sigmas = (float(odom_noise[0]), float(np.deg2rad(odom_noise[1])))
            if variance_n2 is not None:
                var = [float(np.interp(t, img_ns, variance_n2[:, j])) for j in (0, 1)]
                # floored so that the first pose's covariance reads as filled (ROS: all zeros = unknown)
                sigmas = tuple(max(float(np.sqrt(s0 ** 2 + v)), COVARIANCE_FLOOR_SIGMA) for s0, v in zip(sigmas, var))
            twist = None
            if twist_n2 is not None:
                twist = np.diag([float(np.interp(t, img_ns, twist_n2[:, j])) for j in (0, 0, 0, 1, 1, 1)])
            events.append((int(t), 0, 'odom', (_perturb(T_wb, rng, pos_sigma, rot_sigma), sigmas, twist)))
            odom_count += 1
    for k, t in enumerate(img_ns):
        events.append((int(t), 1, 'image', k))
    if tf_static:
        events.append((min(e[0] for e in events), -1, 'tf_static',
                       mount_links(T_bc, base_frame, camera_frame, camera_link)))
    events.sort(key=lambda e: (e[0], e[1]))

    reliable = qos_profile(True, 10)
    image_format = ''
    iterator: Iterable = events
    if progress:
        from tqdm import tqdm
        iterator = tqdm(events, desc=f'writing {pathlib.Path(path).name}', unit='msg', leave=False)
    with BagWriter(path, storage=storage, overwrite=overwrite) as bag:
        for t, _order, kind, payload in iterator:
            if kind == 'tf_static':
                msg = tf_message([transform_stamped(T, t, parent, child, ROSBAGS) for parent, child, T in payload],
                                 ROSBAGS)
                bag.write(TF_STATIC_TOPIC, TF_MESSAGE, msg, t, qos_profile(True, 1, latched=True))
            elif kind == 'odom':
                T_wb, (position_sigma, rotation_sigma), twist = payload
                msg = PM.matrix_to_odometry(T_wb, t, base_frame, frame_id=odom_frame, types=ROSBAGS,
                                           position_sigma=position_sigma, rotation_sigma=rotation_sigma,
                                           twist_covariance_66=twist)
                bag.write(odom_topic, ODOMETRY, msg, t, reliable)
            else:
                rgb = np.asarray(seq.image(idx[payload]))
                info = M.K_to_camera_info(K, rgb.shape[1], rgb.shape[0], t, frame_id=camera_frame, types=ROSBAGS)
                bag.write(camera_info_topic, CAMERA_INFO, info, t, reliable)
                msgtype, img = image_writer(rgb, t, camera_frame)
                bag.write(image_topic, msgtype, img, t, reliable)
                if depth_topic:
                    bag.write(depth_topic, IMAGE, M.depth_to_image(seq.depth(idx[payload]), t, camera_frame,
                                                                   encoding='16UC1', types=ROSBAGS), t, reliable)
                image_format = str(getattr(img, 'format', ''))
    return BagSummary(pathlib.Path(path), storage, len(idx), odom_count, odom_dropped, int(min(e[0] for e in events)),
                      int(max(e[0] for e in events)), img_ns.tolist(), image_topic, image_format)


def _image_writer(compressed: str | None, jpeg_quality: int, encoding: str, image_topic: str | None):
    """write_sequence_bag's image message builder, (rgb, stamp ns, frame) -> (message type, rosbags message), and
    the image topic (default /image, or image_transport's /image/compressed)."""
    if not compressed:
        return (lambda rgb, t, frame: (IMAGE, M.rgb_to_image(rgb, t, frame_id=frame, encoding=encoding,
                                                               types=ROSBAGS))), image_topic or IMAGE_TOPIC
    from dpv_sensor.ros.compressed_image import CODECS, rgb_to_compressed
    if compressed not in CODECS:
        raise BagError(f"compressed must be one of {', '.join(CODECS)}, got {compressed!r}")
    if not 1 <= int(jpeg_quality) <= 100:
        raise BagError(f'jpeg_quality must be in [1, 100], got {jpeg_quality}')
    return (lambda rgb, t, frame: (COMPRESSED_IMAGE, rgb_to_compressed(
        rgb, t, frame_id=frame, codec=compressed, jpeg_quality=jpeg_quality, encoding=encoding, types=ROSBAGS))), \
        image_topic or IMAGE_TOPIC + COMPRESSED_SUFFIX


def mount_links(T_base_camera_44, base_frame: str, camera_frame: str, camera_link: str = '') -> list:
    """The camera mount as TF links [(parent, child, T_parent_child)]: base_frame -> camera_frame, or with
    `camera_link` base_frame -> camera_link (the translation) -> camera_frame (the rotation), as URDFs and camera
    drivers chain them."""
    T = np.asarray(T_base_camera_44, dtype=np.float64)
    if not camera_link:
        return [(base_frame, camera_frame, T)]
    T_base_link, T_link_cam = np.eye(4), np.eye(4)
    T_base_link[:3, 3] = T[:3, 3]
    T_link_cam[:3, :3] = T[:3, :3]
    return [(base_frame, camera_link, T_base_link), (camera_link, camera_frame, T_link_cam)]


# --------------------------------------------------------------------------------------------------------------
# reading
# --------------------------------------------------------------------------------------------------------------
@dataclass
class Stamped:
    """One decoded message: header stamp (ns), frame id, record time (ns) and the numpy payload."""
    stamp_ns: int
    frame_id: str
    data: Any
    log_ns: int
    extra: dict = field(default_factory=dict)

    @property
    def stamp(self) -> float:
        return self.stamp_ns / NS


def _open(path):
    from rosbags.rosbag2 import Reader
    p = pathlib.Path(path)
    if not p.exists():
        raise BagError(f'{p}: no such bag')
    return Reader(p)


def bag_topics(path) -> dict[str, tuple[str, int]]:
    """{topic: (message type, message count)} of a bag. Read once per version of the bag's metadata.yaml (its
    modification time and size): opening a bag parses that YAML, about 0.1 s, and a tool asks for the topics of one
    bag many times (before each topic it reads)."""
    key, version = _metadata_version(path)
    return dict(_read_topics(key) if version is None else _cached_topics(key, version))


def _metadata_version(path) -> tuple[str, tuple[int, int] | None]:
    """(the bag's path, (mtime ns, size) of its metadata.yaml), or None for the version where there is no such file
    (not cached: opening it raises the error)."""
    p = pathlib.Path(path)
    try:
        st = (p / 'metadata.yaml').stat()
    except OSError:
        return str(p), None
    return str(p.resolve()), (st.st_mtime_ns, st.st_size)


@functools.lru_cache(maxsize=64)
def _cached_topics(path: str, _version: tuple[int, int]) -> tuple:
    return _read_topics(path)


def _read_topics(path: str) -> tuple:
    with _open(path) as reader:
        return tuple((c.topic, (c.msgtype, c.msgcount)) for c in reader.connections)


def bag_qos(path) -> dict[str, list]:
    """{topic: offered QoS profiles (rosbags Qos records)} as recorded."""
    with _open(path) as reader:
        return {c.topic: list(getattr(c.ext, 'offered_qos_profiles', []) or []) for c in reader.connections}


def read_messages(path, topics: Iterable[str] | None = None, raw: bool = False
                  ) -> Iterator[tuple[str, str, int, Any]]:
    """Yield (topic, msgtype, record time ns, message) in record-time order; message is the rosbags object,
    or the CDR bytes with raw=True."""
    with _open(path) as reader:
        wanted = None if topics is None else set(topics)
        conns = [c for c in reader.connections if wanted is None or c.topic in wanted]
        if wanted is not None:
            missing = wanted - {c.topic for c in conns}
            if missing:
                have = sorted(c.topic for c in reader.connections)
                raise BagError(f'{path}: no topic {sorted(missing)} (topics: {have})')
        ts = typestore()
        for conn, log_ns, data in reader.messages(connections=conns):
            yield conn.topic, conn.msgtype, log_ns, (bytes(data) if raw else ts.deserialize_cdr(data, conn.msgtype))


def _read(path, topic, expected_type, decode) -> list[Stamped]:
    topics = bag_topics(path)
    if topic not in topics:
        raise BagError(f'{path}: no topic {topic!r} (topics: {sorted(topics)})')
    if topics[topic][0] != expected_type:
        raise BagError(f'{path}: {topic} carries {topics[topic][0]}, expected {expected_type}')
    out = []
    for _t, _ty, log_ns, msg in read_messages(path, [topic]):
        data, extra = decode(msg)
        out.append(Stamped(M.stamp_to_ns(msg.header.stamp), msg.header.frame_id, data, log_ns, extra))
    return out


def read_images(path, topic: str = IMAGE_TOPIC) -> list[Stamped]:
    """Colour images (sensor_msgs/Image, or image_transport's compressed CompressedImage) -> HxWx3 uint8 RGB
    (extra['encoding'] keeps the recorded encoding, extra['format'] a compressed image's format)."""
    if bag_topics(path).get(topic, ('',))[0] == COMPRESSED_IMAGE:
        from dpv_sensor.ros.compressed_image import compressed_to_rgb
        return _read(path, topic, COMPRESSED_IMAGE, lambda m: (compressed_to_rgb(m), {'format': m.format}))
    return _read(path, topic, IMAGE, lambda m: (M.image_to_rgb(m), {'encoding': m.encoding}))


def read_depth_images(path, topic: str = DEPTH_TOPIC) -> list[Stamped]:
    """32FC1 / 16UC1 images -> HxW float32 metres with NaN for no estimate (confidence images read the same)."""
    return _read(path, topic, IMAGE, lambda m: (M.image_to_float(m), {'encoding': m.encoding}))


def read_camera_infos(path, topic: str = CAMERA_INFO_TOPIC) -> list[Stamped]:
    """CameraInfo -> K (3x3); extra['size'] = (width, height)."""
    def decode(m):
        K, size = M.camera_info_to_K(m)
        return K, {'size': size}
    return _read(path, topic, CAMERA_INFO, decode)


def read_odometry(path, topic: str = ODOM_TOPIC) -> list[Stamped]:
    """Odometry -> 4x4 T_world_base (extra['child_frame_id']); invalid messages give a NaN matrix."""
    def decode(m):
        try:
            T = PM.odometry_to_matrix(m)
        except M.BadOdometry:
            T = np.full((4, 4), np.nan)
        return T, {'child_frame_id': m.child_frame_id}
    return _read(path, topic, ODOMETRY, decode)


def read_poses(path, topic: str) -> list[Stamped]:
    """PoseStamped -> 4x4."""
    return _read(path, topic, POSE_STAMPED, lambda m: (PM.pose_msg_to_matrix(m), {}))


__all__ = ['BagError', 'BagSummary', 'BagWriter', 'ArraySequence', 'Stamped', 'ROSBAGS', 'typestore', 'qos_profile',
           'write_sequence_bag', 'odometry_stamps', 'mount_links', 'as_T_base_camera', 'bag_topics', 'bag_qos',
           'read_messages', 'read_images', 'read_depth_images', 'read_camera_infos', 'read_odometry', 'read_poses',
           'COMPRESSED_IMAGE', 'IMAGE_TOPIC', 'CAMERA_INFO_TOPIC', 'ODOM_TOPIC', 'DEPTH_TOPIC', 'CONFIDENCE_TOPIC',
           'DEPTH_INFO_TOPIC']
