"""`ros2 run dpv_sensor node`: the rclpy adapter of the virtual depth camera.

This module owns ROS plumbing only: parameters, QoS, subscriptions, publishing, diagnostics, signals.
"""
from __future__ import annotations

import argparse
import sys

from dpv_sensor import params as P

NODE_NAME = 'dpv_sensor'


def self_check() -> int:
    """Import every heavy dependency the node needs and print versions; 0 when all import."""
    failures = []
    versions = {}
    for mod in ('rclpy', 'torch', 'cv2', 'gtsam', 'numpy', 'rosbags', 'safetensors',
                'sensor_msgs.msg', 'nav_msgs.msg', 'diagnostic_msgs.msg'):
        try:
            m = __import__(mod, fromlist=['_'])
            versions[mod] = getattr(m, '__version__', 'ok')
        except Exception as exc:  # report every missing piece, not only the first
            failures.append(f'{mod}: {exc}')
    for mod, ver in versions.items():
        print(f'  {mod:22s} {ver}')
    try:
        P.validate(P.defaults())
    except P.ParameterError as exc:
        failures.append(f'default parameters: {exc}')
    if failures:
        print('self-check FAILED:\n  ' + '\n  '.join(failures), file=sys.stderr)
        return 1
    print('self-check ok')
    return 0


def _descriptor(spec: P.ParamSpec):
    from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor)
    desc = ParameterDescriptor(name=spec.name, description=spec.description, read_only=True)
    if spec.choices:
        desc.additional_constraints = 'one of: ' + ', '.join(map(str, spec.choices))
    if spec.kind is float and (spec.min_value is not None or spec.max_value is not None):
        desc.floating_point_range = [FloatingPointRange(
            from_value=float(spec.min_value if spec.min_value is not None else -1e300),
            to_value=float(spec.max_value if spec.max_value is not None else 1e300), step=0.0)]
    if spec.kind is int and (spec.min_value is not None or spec.max_value is not None):
        desc.integer_range = [IntegerRange(
            from_value=int(spec.min_value if spec.min_value is not None else -(2 ** 62)),
            to_value=int(spec.max_value if spec.max_value is not None else 2 ** 62), step=1)]
    return desc


def declare_parameters(node) -> dict:
    """Declare every parameter of params.SPECS on `node` and return their validated values."""
    from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
    for spec in P.SPECS:
        try:
            node.declare_parameter(spec.name, spec.default, _descriptor(spec))
        except (InvalidParameterTypeException, InvalidParameterValueException) as exc:
            raise P.ParameterError(f"parameter '{spec.name}' rejected: {exc}") from None
    values = {spec.name: node.get_parameter(spec.name).value for spec in P.SPECS}
    return P.validate(values)


def _node_base():
    from rclpy.node import Node
    return Node


class DepthCameraNode(_node_base()):
    """The virtual depth camera on the ROS graph (parameters, topics, diagnostics)."""

    def __init__(self, **kwargs):
        super().__init__(NODE_NAME, **kwargs)
        self.config = declare_parameters(self)
        self.get_logger().info(
            f"ready: preset={self.config['preset']} device={self.config['device']} "
            f"filter={self.config['filter_mode']} odometry={self.config['odometry']}")

    def close(self) -> None:
        """Release workers and resources before the node is destroyed."""


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv if argv is None else argv
    parser = argparse.ArgumentParser(
        prog='node', description='dpv_sensor: virtual RGB-D camera from monocular RGB + odometry. '
        'ROS arguments go after --ros-args, e.g. --ros-args --params-file config/dpv_sensor.yaml')
    parser.add_argument('--check', action='store_true', help='import all dependencies, validate defaults, exit')
    import rclpy.utilities
    own_args = rclpy.utilities.remove_ros_args(argv)[1:]
    args = parser.parse_args(own_args)
    if args.check:
        return self_check()

    import rclpy
    from rclpy.executors import ExternalShutdownException

    rclpy.init(args=argv)  # installs SIGINT and SIGTERM handlers that shut the context down
    node = None
    try:
        node = DepthCameraNode()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except P.ParameterError as exc:
        print(f'[{NODE_NAME}] invalid parameter: {exc}', file=sys.stderr)
        return 2
    finally:
        if node is not None:
            node.close()
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
