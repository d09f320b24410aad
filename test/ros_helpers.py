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
    """Start `python -m dpv_sensor.node` (or `executable`) as a separate process with its output captured."""
    cmd = (executable or [sys.executable, '-m', 'dpv_sensor.node']) + (args or [])
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
