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
               env: dict | None = None) -> subprocess.Popen | ForkedNode:
    """Start `python -m dpv_sensor.ros.node` (or `executable`) as a separate process with its output captured.

    The node (or the module of an `executable` `python -m MODULE`) is forked from the session's fork server
    (fork_starts.py: the imports are paid once), unless DPV_TEST_FORK_NODES=0; either way its own process with the
    same environment, command line, signals, exit code and output."""
    full_env = dict(os.environ)
    full_env.update(env or {})
    full_env.setdefault('PYTHONUNBUFFERED', '1')
    module = 'dpv_sensor.ros.node' if executable is None else \
        executable[2] if len(executable) == 3 and executable[:2] == [sys.executable, '-m'] else None
    if module is not None and os.environ.get('DPV_TEST_FORK_NODES', '1') != '0':
        return _fork_server().start(module, list(args or []), full_env)
    cmd = (executable or [sys.executable, '-m', 'dpv_sensor.ros.node']) + (args or [])
    return subprocess.Popen(cmd, cwd=REPO, env=full_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)


def launch_replay_node(command: list[str], env: dict, log_path: pathlib.Path) -> subprocess.Popen | ForkedNode:
    """The tools' replay launcher (`client.replay.run_node_replay(launch=...)`) for tests: the node's
    `python -m MODULE ARGS` forked from the session's fork server, as `start_node` does (a fresh interpreter with
    DPV_TEST_FORK_NODES=0)."""
    if command[:2] == [sys.executable, '-m'] and os.environ.get('DPV_TEST_FORK_NODES', '1') != '0':
        return _fork_server().start(command[2], command[3:], env, log=pathlib.Path(log_path).resolve())
    from dpv_sensor.client.node_process import launch_process
    return launch_process(command, env, log_path)


class ForkedNode:
    """A node process forked by the fork server, with the part of subprocess.Popen the tests use."""

    def __init__(self, server: '_ForkServer', pid: int, log: pathlib.Path, args: list[str]):
        self.server, self.pid, self.log, self.args = server, pid, log, args

    @property
    def returncode(self) -> int | None:
        return self.server.codes.get(self.pid)

    def poll(self) -> int | None:
        return self.returncode

    def send_signal(self, sig) -> None:
        if self.poll() is None:
            os.kill(self.pid, sig)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)

    def wait(self, timeout: float | None = None) -> int:
        with self.server.cond:
            if not self.server.cond.wait_for(lambda: self.returncode is not None or self.server.dead, timeout):
                raise subprocess.TimeoutExpired(['node'] + self.args, timeout)
        if self.returncode is None:
            raise RuntimeError('the fork server died: ' + self.server.stderr_text())
        return self.returncode

    def communicate(self, timeout: float | None = None) -> tuple[str, None]:
        self.wait(timeout)
        return self.log.read_text(errors='replace'), None


class _ForkServer:
    """fork_starts.py --serve for this test session: forks node processes on request and reports their exits."""

    def __init__(self):
        import tempfile
        import threading
        self.dir = pathlib.Path(tempfile.mkdtemp(prefix='dpv_test_nodes_'))
        self.cond = threading.Condition()
        self.pids: dict[int, int] = {}
        self.codes: dict[int, int] = {}
        self.dead = False
        self.count = 0
        self.stderr = open(self.dir / 'server.log', 'w')
        env = dict(os.environ, PYTHONUNBUFFERED='1')
        self.proc = subprocess.Popen([sys.executable, str(REPO / 'test' / 'fork_starts.py'), '--serve'], cwd=REPO,
                                     env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self.stderr,
                                     text=True)
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        import json
        for line in self.proc.stdout:
            msg = json.loads(line)
            with self.cond:
                if 'id' in msg:
                    self.pids[msg['id']] = msg['pid']
                else:
                    self.codes[msg['pid']] = msg['code']
                self.cond.notify_all()
        with self.cond:
            self.dead = True
            self.cond.notify_all()

    def stderr_text(self) -> str:
        return (self.dir / 'server.log').read_text(errors='replace')

    def start(self, module: str, args: list[str], env: dict, kind: str = 'module',
              log: pathlib.Path | None = None) -> ForkedNode:
        """Fork `python -m module args` (kind 'console': the node's console script with args) in `env`, its
        output to `log` (default: a file of the server's folder)."""
        import json
        self.count += 1
        n, log = self.count, log or self.dir / f'node_{self.count:03d}.log'
        self.proc.stdin.write(json.dumps({'id': n, 'kind': kind, 'module': module, 'args': args, 'env': env,
                                          'log': str(log)}) + '\n')
        self.proc.stdin.flush()
        with self.cond:
            if not self.cond.wait_for(lambda: n in self.pids or self.dead, 120.0) or n not in self.pids:
                raise RuntimeError('the fork server did not start the node: ' + self.stderr_text())
            return ForkedNode(self, self.pids[n], log, args)

    def close(self) -> None:
        import shutil
        if self.proc.poll() is None:
            self.proc.stdin.close()          # the server kills what still runs and exits
            try:
                self.proc.wait(30.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
        self.stderr.close()
        shutil.rmtree(self.dir, ignore_errors=True)


_SERVER: list[_ForkServer] = []


def _fork_server() -> _ForkServer:
    if not _SERVER or _SERVER[0].dead:
        import atexit
        _SERVER[:] = [_ForkServer()]
        atexit.register(_SERVER[0].close)
    return _SERVER[0]


def spare_domain() -> int:
    """A second DDS domain of this worker's own, for a test that runs two ROS graphs at once: 201..231, apart from
    the workers' 100..200 (conftest), and different for two workers whose domains are neighbours."""
    return 201 + (int(os.environ['ROS_DOMAIN_ID']) - 100) % 31


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



def forked_node_starts(starts: list[tuple[str, list[str]]], parallel: int = 4,
                       timeout: float = 300.0) -> list[tuple[int, str]]:
    """Run the node's command lines `starts` = [(kind 'module' | 'console', args after the program)], `parallel` at a
    time, each as its own process forked by the session's fork server; their (exit code, output) in order."""
    env = dict(os.environ, PYTHONUNBUFFERED='1')
    server = _fork_server()
    procs: list[ForkedNode] = []
    for kind, args in starts:
        running = [p for p in procs if p.poll() is None]
        if len(running) >= parallel:
            running[0].wait(timeout)
        procs.append(server.start('dpv_sensor.ros.node', list(args), env, kind=kind))
    return [(p.wait(timeout), p.communicate(timeout)[0]) for p in procs]
