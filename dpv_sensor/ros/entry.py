"""`ros2 run dpv_sensor node`: the console script, light on purpose. It runs the start-up steps of
``dpv_sensor.ros.startup`` (signal handlers, DDS transport, malloc settings: standard library only) before it imports
the node module (``dpv_sensor.ros.node``: rclpy, torch, OpenCV), then runs the node."""
from __future__ import annotations

from dpv_sensor.ros import startup


def _load_node() -> startup.NodeFunctions:
    from dpv_sensor.ros import node   # the heavy imports, after the start-up steps
    return node.run, node.self_check


def main(argv: list[str] | None = None) -> int:
    """The node program (``startup.main``); returns the exit code."""
    return startup.main(argv, _load_node)


def console_main() -> None:
    """`ros2 run dpv_sensor node` (setup.py console script)."""
    startup.exit_process(main())
