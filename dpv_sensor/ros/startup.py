"""The node process's start-up steps before the heavy imports (standard library only, on purpose).

Start-up order, so that a signal at any moment gives a clean exit 0 and a failed start exits 2 with one message:

1. ``install_signal_handlers()``: SIGINT / SIGTERM set :data:`STOP` (no exception is ever raised into an import or
   into the node's construction). Nothing heavy is imported before this: this module imports only the standard
   library.
2. ``apply_transport_settings()``: the node's own DDS transport (``dpv_sensor.ros.transport``: the Fast DDS profile in
   config/, unless the user chose a transport) goes into the process environment before rclpy is imported, since
   the middleware reads it when rclpy initialises; and glibc's malloc arenas are capped and its mmap threshold
   pinned before any thread exists (``process_memory``).
3. the node module is imported (rclpy, torch, OpenCV: seconds on a loaded machine). A signal meanwhile ends the
   process at once with exit 0: nothing runs yet that needs stopping (no ROS context, no node, no file written),
   so it does not wait for the imports to finish (:func:`imports_done` ends this step).
4. ``dpv_sensor.ros.node.run(argv, STOP)`` builds and spins the node until STOP is set or the node reports a fatal
   start-up error (exit 2).

Two ways in run these steps: the console script (``dpv_sensor.ros.entry``, which imports the node module at step 3)
and ``python -m dpv_sensor.ros.node`` (the node module calls :func:`prepare` before its own heavy imports).
"""
from __future__ import annotations

import os
import signal
import sys
import threading
from typing import Callable, Tuple

# set by SIGINT / SIGTERM (once installed); the node's spin loop polls it
STOP = threading.Event()
_installed = False
# until the node module's imports are done (step 3), a signal ends the process at once
_importing = True
# what configure_malloc() put in force (logged by the node), None before prepare()
MALLOC_NOTE: str | None = None
# what apply_transport_settings() did (logged by the node), None before it ran
TRANSPORT_NOTE: str | None = None

# the node module's (run(argv, stop) -> exit code, self_check() -> exit code), imported at step 3
NodeFunctions = Tuple[Callable[[list, threading.Event], int], Callable[[], int]]


def _on_signal(_signum, _frame) -> None:
    STOP.set()
    if _importing:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, RuntimeError, ValueError):   # a write the signal interrupted, a closed stream
                pass
        os._exit(0)


def imports_done() -> None:
    """The end of step 3: from now on a signal only sets :data:`STOP`, and the node stops itself."""
    global _importing
    _importing = False


def install_signal_handlers() -> None:
    """SIGINT and SIGTERM set :data:`STOP` from now on (idempotent). A process started with SIGINT ignored (a
    background job of a non-interactive shell) gets the handler too: ``ros2 run ... &`` then stops on SIGINT."""
    global _installed
    if _installed:
        return
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, _on_signal)
    _installed = True


def apply_transport_settings() -> str:
    """The node's DDS transport settings (``dpv_sensor.ros.transport.configure``: the Fast DDS profile, unless the user
    chose a transport), applied to this process's environment before rclpy is imported so that they reach the
    middleware. Idempotent; returns the line the node logs."""
    global TRANSPORT_NOTE
    if TRANSPORT_NOTE is None:
        from dpv_sensor.ros.transport import configure   # standard library only
        TRANSPORT_NOTE = configure()
    return TRANSPORT_NOTE


def malloc_note() -> str:
    """glibc's malloc settings in force (set by :func:`prepare` before any thread existed; now otherwise)."""
    global MALLOC_NOTE
    if MALLOC_NOTE is None:
        from dpv_sensor.ros.process_memory import configure_malloc   # standard library only
        MALLOC_NOTE = configure_malloc()
    return MALLOC_NOTE


def own_args(argv: list[str]) -> list[str]:
    """The program's own arguments: argv[1:] without the ROS arguments (``--ros-args ... [--]``), found without
    importing rclpy (the same rule as ``rclpy.utilities.remove_ros_args``)."""
    out: list[str] = []
    in_ros = False
    for arg in argv[1:]:
        if arg == '--ros-args':
            in_ros = True
        elif in_ros and arg == '--':
            in_ros = False
        elif not in_ros:
            out.append(arg)
    return out


def prepare() -> None:
    """Steps 1 and 2 of the module docstring (idempotent)."""
    install_signal_handlers()
    apply_transport_settings()
    malloc_note()


def main(argv: list[str] | None, load: Callable[[], NodeFunctions]) -> int:
    """The program: steps 1 and 2, the arguments, then ``load()`` (step 3: the node module's ``run`` and
    ``self_check``) and ``run`` (step 4), or ``self_check`` with ``--check``."""
    prepare()
    argv = list(sys.argv if argv is None else argv)
    import argparse
    parser = argparse.ArgumentParser(
        prog='node', description='dpv_sensor: virtual RGB-D camera from monocular RGB + odometry. '
        'ROS arguments go after --ros-args, e.g. --ros-args --params-file config/dpv_sensor.yaml')
    parser.add_argument('--check', action='store_true', help='import all dependencies, validate defaults, exit')
    args = parser.parse_args(own_args(argv))
    if STOP.is_set():
        return 0
    run, self_check = load()          # the heavy imports (rclpy, torch, OpenCV)
    imports_done()
    if args.check:
        return self_check()
    if STOP.is_set():
        return 0
    return run(argv, STOP)


def exit_process(code: int) -> None:
    """Leave with `code` without the interpreter's teardown of its modules: the node has shut ROS down already, and
    tearing down the libraries it loaded adds nothing but time (PyTorch's alone 0.7-1 s after every stop). The exit
    handlers run (log handlers flush) unless a worker thread is still busy (e.g. loading weights when the stop came),
    where they and the teardown could print a traceback; then Python's and C's output streams are flushed."""
    import atexit
    import ctypes
    busy = [t for t in threading.enumerate() if t is not threading.main_thread() and t.is_alive() and t.daemon]
    try:
        if not busy:
            atexit._run_exitfuncs()
    finally:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):       # a closed or broken pipe: nothing more can be said on it
                pass
        try:
            ctypes.CDLL(None).fflush(None)      # what the C libraries (ROS's console logging) still buffer
        except (OSError, AttributeError):
            pass
        os._exit(code)
