"""The node's command lines as children of one parent that has already imported what every start imports (torch,
rclpy and the message packages, OpenCV, the node module's own imports).

Each child is a process of its own that runs exactly what `python -m dpv_sensor.ros.node ARGS` ('module') or the
console script of `ros2 run dpv_sensor node ARGS` ('console') runs after the imports, from the entry point's signal
handlers to its exit code and the interpreter's own shutdown, without paying the seconds of imports again: for tests
of starts whose outcome does not depend on the imports' timing (a signal during the imports needs a real start).

    python test/fork_starts.py JOBS_JSON PARALLEL     JOBS_JSON: [[kind, [args...], log path], ...]

Each child's stdout and stderr go to its log; the parent prints the exit codes, in order, as one JSON line.
"""
import json
import os
import runpy
import sys

import cv2  # noqa: F401
import diagnostic_msgs.msg  # noqa: F401
import geometry_msgs.msg  # noqa: F401
import nav_msgs.msg  # noqa: F401
import numpy  # noqa: F401
import rclpy  # noqa: F401
import safetensors.torch  # noqa: F401
import sensor_msgs.msg  # noqa: F401
import torch  # noqa: F401

import dpv_sensor.ros.node  # noqa: F401


def child(kind: str, args: list, log: str) -> None:
    """In the forked child: output to `log`, then the entry point; its SystemExit ends this process."""
    fd = os.open(log, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    if kind == 'module':
        sys.argv = ['node'] + args
        del sys.modules['dpv_sensor.ros.node']     # runs afresh as __main__, its imports already loaded
        runpy.run_module('dpv_sensor.ros.node', run_name='__main__', alter_sys=True)
    else:
        sys.argv = ['-c'] + args
        from dpv_sensor.ros.entry import console_main
        sys.exit(console_main())
    sys.exit(0)


def main() -> None:
    jobs, parallel = json.loads(sys.argv[1]), int(sys.argv[2])
    running, codes = {}, {}
    for n, (kind, args, log) in enumerate(jobs):
        while len(running) >= parallel:
            pid, status = os.wait()
            codes[running.pop(pid)] = os.waitstatus_to_exitcode(status)
        pid = os.fork()
        if pid == 0:
            child(kind, args, log)
        running[pid] = n
    while running:
        pid, status = os.wait()
        codes[running.pop(pid)] = os.waitstatus_to_exitcode(status)
    print(json.dumps([codes[n] for n in range(len(jobs))]))


if __name__ == '__main__':
    main()
