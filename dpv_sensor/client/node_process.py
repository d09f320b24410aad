"""Helpers the tools share for running the node as a child process, talking to it from a client node of their
own, and reading its memory from /proc."""
from __future__ import annotations

import pathlib
import sys
from typing import Any, Callable, Dict, List

#: how a tool starts the node's command line as its own process: ``(command, env, log_path) -> handle`` with the
#: part of :class:`subprocess.Popen` the tools use (``pid``, ``poll``, ``returncode``, ``send_signal``, ``wait``,
#: ``kill``), the process's stdout and stderr going to ``log_path``
Launcher = Callable[[List[str], Dict[str, str], pathlib.Path], Any]


def node_command(params: Dict[str, Any], remaps: Dict[str, str]) -> List[str]:
    """`python -m dpv_sensor.ros.node --ros-args -p k:=v ... -r a:=b ...` for these parameters and remaps."""
    cmd = [sys.executable, '-m', 'dpv_sensor.ros.node', '--ros-args']
    for k, v in params.items():
        if isinstance(v, bool):
            v = 'true' if v else 'false'
        elif isinstance(v, (list, tuple)):
            v = '[' + ','.join(repr(float(x)) for x in v) + ']'
        elif isinstance(v, str) and v == '':
            v = "''"
        cmd += ['-p', f'{k}:={v}']
    for a, b in remaps.items():
        cmd += ['-r', f'{a}:={b}']
    return cmd


def launch_process(command: List[str], env: Dict[str, str], log_path: pathlib.Path):
    """The default :data:`Launcher`: a fresh interpreter (:class:`subprocess.Popen`) in the repository's folder,
    stdout and stderr to ``log_path``."""
    import subprocess
    with open(log_path, 'w') as log:
        return subprocess.Popen(command, cwd=pathlib.Path(__file__).resolve().parents[2], env=env, stdout=log,
                                stderr=subprocess.STDOUT)


class ClientNode:
    """A node of the tool's own (bag player, output collector) in a private rclpy context.

    The context is initialised with no command-line arguments: rclpy would otherwise read the tool's own argv,
    where a `--param name:=value` meant for the node under test is taken for a (deprecated) remap rule. There are
    no rclpy signal handlers, so Ctrl-C stays a KeyboardInterrupt in the tool (and reaches the node process, in
    the same process group, as its own SIGINT)."""

    def __init__(self, name: str):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions
        self._rclpy = rclpy
        self.context = rclpy.context.Context()
        rclpy.init(args=[], context=self.context, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def close(self) -> None:
        """Idempotent."""
        if self.executor is not None:
            self.executor.shutdown()
            self.node.destroy_node()
            self.executor = None
        if self.context.ok():
            self._rclpy.shutdown(context=self.context)
