"""A camera + odometry publisher driving the node process frame by frame, for tests that need to control exactly
what arrives: stamps, rates, broken images, frame ids. Each `send` publishes odometry and camera_info at the
image's stamp, then the image; `wait_accounted` waits until /diagnostics has accounted for n images."""
from __future__ import annotations

import numpy as np

from ros_helpers import start_node, stop_process, wait_for
from dpv_sensor.ros import msgs as M
from dpv_sensor.ros import pose_msgs as PM
from dpv_sensor.stream.pose_buffer import NS

W, H = 160, 128
BASE_NS = 1_760_000_000 * NS
FAST_PARAMS = {'measurement': 'classical', 'processing_width': W, 'processing_height': H, 'num_planes': 32,
               'keyframe_max_interval': 1, 'input_depth': 50, 'diagnostics_period': 0.1,
               # the driver sends each image's odometry just before it, but on a loaded 2-core machine the node may
               # take the image first and hear the odometry later than the 0.5 s default: a test of late odometry sets
               # its own timeout
               'odom_wait_timeout': 3.0,
               # the odometry of 'base_link' tracks the camera 'cam' itself: the identity mount, not looked up on TF
               'extrinsic_source': 'parameter'}
# for a test that sends its images one at a time and waits for each on /diagnostics: the period paces the test
ONE_AT_A_TIME = {'diagnostics_period': 0.05}


class StreamDriver:
    """Publishes a rendered sequence to a node process started with `args` (the node's command line after
    `python -m dpv_sensor.ros.node`); topics: the absolute names the node is expected to subscribe; image_type: the
    image publisher's message type (default sensor_msgs/Image; send `image_msg` of another type)."""

    def __init__(self, args: list[str], topics: dict | None = None, frames: int = 40, seed: int = 4,
                 reliability: str = 'reliable', name: str = 'stream_driver', env: dict | None = None,
                 namespace: str = '', depth: int = 50, image_type=None):
        from nav_msgs.msg import Odometry
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import CameraInfo, Image

        from dpv_sensor.client.node_process import ClientNode
        from dpv_sensor.client.ros_io import OutputCollector
        from dpv_sensor.data.synthetic import render_sequence
        topics = topics or {'image': '/image', 'camera_info': '/camera_info', 'odom': '/odom'}
        self.seq = render_sequence(seed, frames, width=W, height=H)
        self.client = ClientNode(name)
        self.node, self.executor = self.client.node, self.client.executor
        rel = ReliabilityPolicy.RELIABLE if reliability == 'reliable' else ReliabilityPolicy.BEST_EFFORT
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=rel,
                         durability=DurabilityPolicy.VOLATILE)
        types = {'image': image_type or Image, 'camera_info': CameraInfo, 'odom': Odometry}
        self.pubs = {k: self.node.create_publisher(types[k], t, qos) for k, t in topics.items()}
        self.outputs = OutputCollector(self.node, namespace=namespace)
        self.reliability = reliability
        self.proc = start_node(args, env={'OMP_NUM_THREADS': '1', **(env or {})})
        self.log = ''
        self.code = None

    def spin(self, t: float) -> None:
        self.executor.spin_once(timeout_sec=t)

    def diag(self, key: str, default: int = 0) -> int:
        return self.outputs.diag_int(key, default)

    def accounted(self) -> int:
        return self.diag('frames_processed') + self.diag('dropped_total')

    def wait_ready(self, timeout: float = 90.0) -> None:
        """The estimator is built, every input is subscribed at the publishers' reliability (input_reliability auto
        re-subscribes once it has seen them: what is sent meanwhile is lost) and matched both ways, and the collector
        hears the outputs."""
        out = self.outputs
        ok = wait_for(lambda: out.diagnostics.get('measurement_model', 'starting') != 'starting'
                      and all(out.diagnostics.get(f'input_qos.{k}') == self.reliability for k in self.pubs)
                      and all(self.diag(f'publishers.{k}') == 1 for k in self.pubs)
                      and all(p.get_subscription_count() == 1 for p in self.pubs.values())
                      and out.subs[0].get_publisher_count() == 1, timeout=timeout, spin=self.spin)
        assert self.proc.poll() is None, 'node exited early:\n' + self.stop()
        assert ok, f'the node never got ready: {out.diagnostics}'

    def stamp_ns(self, i: int, rate: float = 30.0) -> int:
        return BASE_NS + int(round(i * NS / rate))

    def send(self, i: int, stamp_ns: int, image=None, frame_id: str = 'cam', odom_frame: str = 'odom',
             image_msg=None) -> None:
        """Odometry and camera_info at `stamp_ns`, then frame i's image (or `image`, or the message `image_msg`)."""
        k = i % len(self.seq)
        if 'odom' in self.pubs:
            self.pubs['odom'].publish(PM.matrix_to_odometry(self.seq.pose(k), stamp_ns, 'base_link', odom_frame))
        if 'camera_info' in self.pubs:
            self.pubs['camera_info'].publish(M.K_to_camera_info(self.seq.K, W, H, stamp_ns, frame_id))
        if image_msg is None:
            rgb = self.seq.image(k) if image is None else image
            image_msg = M.rgb_to_image(rgb, stamp_ns, frame_id)
        self.pubs['image'].publish(image_msg)

    def send_odom(self, i: int, stamp_ns: int, odom_frame: str = 'odom') -> None:
        self.pubs['odom'].publish(PM.matrix_to_odometry(self.seq.pose(i % len(self.seq)), stamp_ns, 'base_link',
                                                       odom_frame))

    def wait_accounted(self, n: int, timeout: float = 60.0) -> bool:
        return wait_for(lambda: self.accounted() >= n, timeout=timeout, spin=self.spin)

    def wait_diagnostics(self, ticks: int = 2, timeout: float = 10.0) -> dict:
        """`ticks` more /diagnostics messages, then the latest values."""
        count = self.outputs.diagnostics_count
        wait_for(lambda: self.outputs.diagnostics_count >= count + ticks, timeout=timeout, spin=self.spin)
        return dict(self.outputs.diagnostics)

    def stop(self) -> str:
        if self.code is None:
            self.code, self.log = stop_process(self.proc)
            self.client.close()
        return self.log


def params_args(params: dict, remaps: dict | None = None) -> list[str]:
    """`--ros-args -p k:=v ... -r a:=b ...`."""
    return ['--ros-args'] + [a for k, v in params.items() for a in ('-p', f'{k}:={v}')] + \
        [a for k, v in (remaps or {}).items() for a in ('-r', f'{k}:={v}')]


def lens_cap(rng: np.random.Generator, level: float, noise: float) -> np.ndarray:
    """A nearly uniform frame: `level` (0-255) plus Gaussian sensor noise of std `noise`."""
    return np.clip(rng.normal(level, noise, size=(H, W, 3)), 0, 255).astype(np.uint8)
