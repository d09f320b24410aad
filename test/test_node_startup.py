"""Start-up of the node process: a start that cannot succeed always exits 2 with its one message, and SIGINT or
SIGTERM at any moment of the start-up (or later) gives exit 0 without a traceback, for both entry points
(`python -m dpv_sensor.ros.node` and the console script `ros2 run dpv_sensor node` runs)."""
import os
import re
import signal
import subprocess
import sys
import time

import pytest

from ros_helpers import REPO, forked_node_starts

MODULE = [sys.executable, '-m', 'dpv_sensor.ros.node']
# what the console script setuptools writes for `ros2 run dpv_sensor node` does
CONSOLE = [sys.executable, '-c', 'import sys; from dpv_sensor.ros.entry import console_main; sys.exit(console_main())']
MISSING_WEIGHTS = ['--ros-args', '-p', 'measurement:=network', '-p', 'weights:=/nonexistent/x.safetensors']


def _default_signals():
    # a background job of a non-interactive shell starts with SIGINT ignored, and children inherit that
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _spawn(cmd):
    env = dict(os.environ, PYTHONUNBUFFERED='1')
    return subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            preexec_fn=_default_signals)


def test_missing_weights_with_network_measurement_exits_2_every_time():
    """20 starts (both entry points, four at a time): the worker's failure never races the main thread. The starts
    are forked from a parent that has imported what a start imports: the race is in the start-up after them."""
    starts = [('module' if i % 2 == 0 else 'console', MISSING_WEIGHTS) for i in range(20)]
    results = forked_node_starts(starts, parallel=4)
    bad = [(i, code, out) for i, (code, out) in enumerate(results)
           if code != 2 or 'Traceback' in out or 'cannot build the estimator' not in out]
    assert not bad, '\n\n'.join(f'run {i}: exit {code}\n{out}' for i, code, out in bad[:3])
    for _code, out in results:
        assert 'nonexistent/x.safetensors' in out
        # one message, and never 'ready' for a node that is about to exit
        assert out.count('cannot build the estimator') == 1, out
        assert not re.search(r'\bready\b', out), out


@pytest.mark.parametrize('delay', [0.2, 0.5, 1.0, 1.5, 3.0])
@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM], ids=['SIGINT', 'SIGTERM'])
def test_signal_during_start_up_exits_0_without_traceback(sig, delay):
    cmd = (MODULE if delay in (0.2, 1.0, 3.0) else CONSOLE)
    proc = _spawn(cmd)
    time.sleep(delay)
    sent = proc.poll() is None
    if sent:
        proc.send_signal(sig)
    try:
        out, _ = proc.communicate(timeout=60.0)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
        pytest.fail(f'no exit within 60 s of {sig.name} at {delay} s:\n{out}')
    assert sent, f'the node exited on its own before the signal:\n{out}'
    assert proc.returncode == 0, f'{sig.name} at {delay} s: exit {proc.returncode}\n{out}'
    assert 'Traceback' not in out and 'KeyboardInterrupt' not in out, out


def test_a_signal_during_the_imports_ends_the_process_at_once_and_after_them_only_sets_stop():
    """startup._on_signal: before imports_done() it exits 0 at once (the child below never reaches its own exit 3),
    after it it only sets STOP and the node stops itself."""
    from dpv_sensor.ros import startup
    assert startup._importing
    pid = os.fork()
    if pid == 0:                                   # the child: a signal arrives while the node module is imported
        try:
            startup._on_signal(signal.SIGINT, None)
        finally:
            os._exit(3)
    _, status = os.waitpid(pid, 0)
    assert os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0, status
    try:
        startup.imports_done()
        startup._on_signal(signal.SIGTERM, None)
        assert startup.STOP.is_set()
    finally:
        startup._importing = True
        startup.STOP.clear()
