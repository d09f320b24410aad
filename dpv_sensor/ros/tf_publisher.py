"""TF of the virtual camera (tf2_msgs/msg/TFMessage): its extrinsic on /tf_static, its estimated pose on /tf.

Frames
  static   <base frame> -> <image frame>: the T_base_camera parameter. The base frame is the `base_frame`
           parameter, or else the odometry's child_frame_id; the image frame is the images' header.frame_id.
           Skipped while either is unknown and when the two are the same frame. Published when both names are
           first known and again when one changes, with the QoS of tf2's StaticTransformBroadcaster (reliable,
           transient local, keep last 1), so a subscriber that starts later still receives it. Not published when
           the mount comes from TF itself (extrinsic_source tf): the robot's tree has that frame already, and a
           second publisher of it would duplicate the tree.
  refined  <odometry frame> -> <image frame>_refined: the camera pose the node estimated (pose_refinement window
           or odometry none), stamped with its image, with the QoS of tf2's TransformBroadcaster. A frame of its
           own because the image frame usually has a parent already (the driver's TF or a URDF) and tf2 allows a
           frame one parent only.

The builders work in any message flavour of dpv_sensor.ros.msgs (rclpy or a rosbags typestore); `TfPublisher` owns
the two publishers of a node. tf2_msgs does not come with the ROS 2 wheels on PyPI: `make venv` generates it
(scripts/build_interfaces.sh); `TfPublisher` raises ImportError where it is missing.
"""
from __future__ import annotations

import threading

import numpy as np

from dpv_sensor.ros import msgs as M
from dpv_sensor.stream.pose_buffer import matrix_to_quat

REFINED_SUFFIX = '_refined'
STATIC_TOPIC = '/tf_static'
DYNAMIC_TOPIC = '/tf'


def refined_frame(image_frame: str) -> str:
    """Child frame of the estimated camera pose."""
    return f'{image_frame}{REFINED_SUFFIX}'


def transform_stamped(T_parent_child_44, stamp_ns: int, parent: str, child: str, types: M.MessageTypes = M.ROS):
    """4x4 pose of `child` in `parent` -> geometry_msgs/TransformStamped (quaternion w >= 0)."""
    T = np.asarray(T_parent_child_44, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f'transform {parent} -> {child} is not a finite 4x4 matrix')
    q = matrix_to_quat(T[:3, :3])
    return types('geometry_msgs/msg/TransformStamped', header=M.make_header(stamp_ns, parent, types),
                 child_frame_id=str(child),
                 transform=types('geometry_msgs/msg/Transform',
                                 translation=types('geometry_msgs/msg/Vector3', x=float(T[0, 3]), y=float(T[1, 3]),
                                                   z=float(T[2, 3])),
                                 rotation=types('geometry_msgs/msg/Quaternion', x=float(q[0]), y=float(q[1]),
                                                z=float(q[2]), w=float(q[3]))))


def tf_message(transforms, types: M.MessageTypes = M.ROS):
    return types('tf2_msgs/msg/TFMessage', transforms=list(transforms))


def static_frames(base_frame: str, image_frame: str) -> tuple[str, str] | None:
    """(parent, child) of the static extrinsic, or None when it is not to be published (unknown or same frame)."""
    base, image = (base_frame or '').lstrip('/'), (image_frame or '').lstrip('/')
    if not base or not image or base == image:
        return None
    return base, image


class TfPublisher:
    """The node's TF output: call `frames()` as frame names arrive and `publish_refined()` per estimated pose."""

    def __init__(self, node, T_base_camera_44, base_frame: str | None = None):
        """`T_base_camera_44` None: the mount comes from TF, no static transform is published."""
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
        from tf2_msgs.msg import TFMessage   # ImportError where tf2_msgs was not generated

        self._node = node
        self._T_base_camera = None if T_base_camera_44 is None else np.asarray(T_base_camera_44, dtype=np.float64)
        self._base_param = base_frame or ''
        self._lock = threading.Lock()
        self._base = ''
        self._image = ''
        self.static_published: tuple[str, str] | None = None   # (parent, child) on /tf_static now
        self.refined_published = 0
        static_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                                durability=DurabilityPolicy.TRANSIENT_LOCAL)
        dynamic_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
                                 durability=DurabilityPolicy.VOLATILE)
        self.pub_static = node.create_publisher(TFMessage, STATIC_TOPIC, static_qos)
        self.pub_dynamic = node.create_publisher(TFMessage, DYNAMIC_TOPIC, dynamic_qos)

    def frames(self, image_frame: str | None = None, odom_child_frame: str | None = None) -> None:
        """New frame names from an image header or an odometry child_frame_id; (re)publishes the static TF."""
        with self._lock:
            if image_frame is not None:
                self._image = image_frame
            if odom_child_frame is not None:
                self._base = odom_child_frame
            if self._T_base_camera is None:
                return
            pair = static_frames(self._base_param or self._base, self._image)
            if pair is None or pair == self.static_published:
                return
            stamp_ns = self._node.get_clock().now().nanoseconds
            self.pub_static.publish(tf_message([transform_stamped(self._T_base_camera, stamp_ns, *pair)]))
            self.static_published = pair
        self._node.get_logger().info(f'TF: {pair[0]} -> {pair[1]} (T_base_camera) on {STATIC_TOPIC}')

    def publish_refined(self, T_world_cam_44, stamp_ns: int, world_frame: str, image_frame: str) -> None:
        self.pub_dynamic.publish(tf_message([transform_stamped(T_world_cam_44, stamp_ns, world_frame.lstrip('/'),
                                                               refined_frame(image_frame.lstrip('/')))]))
        self.refined_published += 1

    def status(self) -> str:
        """One line for /diagnostics."""
        static = ('static: none (the camera mount comes from TF)' if self._T_base_camera is None else
                  f'{self.static_published[0]} -> {self.static_published[1]}' if self.static_published else
                  'static: waiting for the base and image frame names' if not self._image or
                  not (self._base_param or self._base) else 'static: skipped (image frame is the base frame)')
        return f'{static}; refined poses {self.refined_published}'
