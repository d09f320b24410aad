"""Node processes forked from one parent that has already imported what every node start imports (torch, OpenCV,
numpy, the stream layer): seconds of imports paid once per test session instead of once per node.

Each child is a process of its own that runs exactly what `python -m dpv_sensor.ros.node ARGS` ('module') or the
console script of `ros2 run dpv_sensor node ARGS` ('console') runs after those imports, in the environment the test
gives it: the entry point's signal handlers, rclpy (imported and initialised in the child: the parent never touches
ROS or DDS), the node, its exit code and the interpreter's own shutdown. A signal during the imports needs a real
start (test_node_startup spawns those itself).

    python test/fork_starts.py --serve    read one request a line on stdin ({"id", "kind", "module", "args", "env",
                                          "log"}), answer {"id", "pid"} when forked and {"pid", "code"} when a child
                                          has exited; on end of input, kill what still runs (ros_helpers.start_node)

Each child's stdout and stderr go to its log; exit codes are those of subprocess (-N: killed by signal N).
"""
import gc
import json
import os
import runpy
import select
import signal
import sys

import cv2  # noqa: F401
import numpy  # noqa: F401
import safetensors.torch  # noqa: F401
import torch

import dpv_sensor.core.rectify  # noqa: F401
import dpv_sensor.stream.pipeline  # noqa: F401


def child(kind: str, module: str, args: list, log: str, env: dict) -> None:
    """In the forked child: its environment, output to `log`, then the entry point (kind 'module': `python -m
    module`); its SystemExit ends the process."""
    os.environ.clear()
    os.environ.update(env)
    if env.get('OMP_NUM_THREADS', '').isdigit():          # read by torch at its import, in the parent
        torch.set_num_threads(int(env['OMP_NUM_THREADS']))
    fd = os.open(log, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    os.close(fd)
    null = os.open(os.devnull, os.O_RDONLY)
    os.dup2(null, 0)
    os.close(null)
    signal.signal(signal.SIGINT, signal.default_int_handler)     # as in a fresh interpreter
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    if kind == 'module':
        sys.argv = [module] + args
        runpy.run_module(module, run_name='__main__', alter_sys=True)
    else:
        sys.argv = ['-c'] + args
        from dpv_sensor.ros.entry import console_main
        sys.exit(console_main())
    sys.exit(0)


def _say(msg: dict) -> None:
    sys.stdout.write(json.dumps(msg) + '\n')
    sys.stdout.flush()


def _reap(children: set) -> None:
    while children:
        try:
            pid, status = os.waitpid(-1, os.WNOHANG)
        except ChildProcessError:
            return
        if pid == 0:
            return
        children.discard(pid)
        _say({'pid': pid, 'code': os.waitstatus_to_exitcode(status)})


def serve() -> None:
    children: set = set()
    buf = b''
    stdin = sys.stdin.fileno()
    while True:
        ready, _, _ = select.select([stdin], [], [], 0.05)
        if ready:
            data = os.read(stdin, 1 << 16)
            if not data:
                break
            buf += data
            while b'\n' in buf:
                line, buf = buf.split(b'\n', 1)
                req = json.loads(line)
                pid = os.fork()
                if pid == 0:
                    child(req['kind'], req['module'], req['args'], req['log'], req['env'])
                children.add(pid)
                _say({'id': req['id'], 'pid': pid})
        _reap(children)
    for pid in children:
        os.kill(pid, signal.SIGKILL)
    for pid in list(children):
        os.waitpid(pid, 0)


if __name__ == '__main__':
    # Everything imported so far moves to the collector's permanent generation: a child's collections and its
    # interpreter's shutdown no longer walk (and copy, page by page) the million objects of torch and the stream
    # layer. A forked start that fails at once took 1.6 s of CPU without it, 0.75 s with it, half of it at the exit.
    gc.collect()
    gc.freeze()
    serve()
