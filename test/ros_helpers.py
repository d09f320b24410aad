"""Helpers for tests that run the node as its own process and watch it over real DDS."""
from __future__ import annotations

import os
import pathlib
import signal
import subprocess
import sys
import time
from typing import Callable

REPO = pathlib.Path(__file__).resolve().parents[1]


def wait_for(condition: Callable[[], bool], timeout: float, spin=None, period: float = 0.05) -> bool:
    """Poll `condition` (spinning `spin(period)` between polls when given) until true or `timeout` s pass."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        if spin is not None:
            spin(period)
        else:
            time.sleep(period)
    return condition()


def start_node(args: list[str] | None = None, executable: list[str] | None = None,
               env: dict | None = None) -> subprocess.Popen:
    """Start `python -m dpv_sensor.ros.node` (or `executable`) as a separate process with its output captured."""
    cmd = (executable or [sys.executable, '-m', 'dpv_sensor.ros.node']) + (args or [])
    full_env = dict(os.environ)
    full_env.update(env or {})
    full_env.setdefault('PYTHONUNBUFFERED', '1')
    return subprocess.Popen(cmd, cwd=REPO, env=full_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)


def wait_exit(proc: subprocess.Popen, timeout: float) -> tuple[int, str]:
    """Wait up to `timeout` s for `proc` to exit and return (exit code, all output); if it has not exited by
    then, kill it and return (-9, its output)."""
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
        return -9, out
    return proc.returncode, out


def stop_process(proc: subprocess.Popen, sig=signal.SIGINT, timeout: float = 20.0) -> tuple[int, str]:
    """Send `sig`, wait for exit and return (exit code, all output). Kills it if it does not stop."""
    if proc.poll() is None:
        proc.send_signal(sig)
    return wait_exit(proc, timeout)


def stop_all(*procs: subprocess.Popen) -> list[tuple[int, str]]:
    """SIGINT every node process (each waited for in turn); their (exit code, output) in order."""
    return [stop_process(p) for p in procs]


def assert_clean_exits(results: list[tuple[int, str]]) -> None:
    """Every stopped node exited with 0 and printed no Python traceback."""
    out = ''.join(o for _, o in results)
    assert all(code == 0 for code, _ in results), out
    assert 'Traceback' not in out, out


def write_rendered_bag(tmp_path_factory, seed: int, frames: int, width: int, height: int, name: str, *,
                       start_ns: int, T_base_camera, camera_frame: str = 'cam_optical', odom_rate: float = 60.0):
    """A rendered sequence written as a rosbag2 with odometry: (sequence, bag path, write summary)."""
    from dpv_sensor.data import rosbag_io as R
    from dpv_sensor.data.synthetic import render_sequence
    seq = render_sequence(seed, frames, width=width, height=height)
    bag = tmp_path_factory.mktemp('bags') / name
    summary = R.write_sequence_bag(bag, seq, odom_rate=odom_rate, start_ns=start_ns, T_base_camera=T_base_camera,
                                   camera_frame=camera_frame, progress=False)
    return seq, bag, summary



def forked_node_starts(starts: list[tuple[str, list[str]]], tmp_dir: pathlib.Path, parallel: int = 4,
                       timeout: float = 300.0) -> list[tuple[int, str]]:
    """Run the node's command lines `starts` = [(kind 'module' | 'console', args after the program)], `parallel` at a
    time, each as its own process forked from one parent that has imported what a start imports (fork_starts.py);
    their (exit code, output) in order."""
    import json
    logs = [str(tmp_dir / f'start_{i:03d}.log') for i in range(len(starts))]
    jobs = [(kind, list(args), log) for (kind, args), log in zip(starts, logs)]
    env = dict(os.environ, PYTHONUNBUFFERED='1')
    res = subprocess.run([sys.executable, str(REPO / 'test' / 'fork_starts.py'), json.dumps(jobs), str(parallel)],
                         cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout)
    assert res.returncode == 0, res.stdout + res.stderr
    codes = json.loads(res.stdout.strip().splitlines()[-1])
    return [(code, pathlib.Path(log).read_text()) for code, log in zip(codes, logs)]
