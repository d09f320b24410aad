"""Shared pytest set-up: ROS logging into a temp dir, an isolated DDS domain per run, data paths."""
from __future__ import annotations

import os
import pathlib
import random
import sys

import pytest

REPO = pathlib.Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / 'shared' / 'data'

# rclpy writes logs under ROS_LOG_DIR; keep them out of $HOME and out of the repo.
os.environ.setdefault('ROS_LOG_DIR', str(REPO / 'log' / 'ros-test'))
# A DDS domain of our own so tests never talk to another ROS graph on the machine (or a parallel run). Under
# pytest-xdist (make test runs three workers) every worker gets a domain of its own: one base per run (the run's id,
# which all its workers share), plus the worker's number (gw0, gw1, ...).
_WORKER = os.environ.get('PYTEST_XDIST_WORKER', '')
if _WORKER.startswith('gw'):
    _BASE = random.Random(os.environ.get('PYTEST_XDIST_TESTRUNUID', '')).randint(0, 100)
    os.environ['ROS_DOMAIN_ID'] = str(100 + (_BASE + int(_WORKER[2:])) % 101)
else:
    os.environ.setdefault('ROS_DOMAIN_ID', str(random.Random(os.getpid()).randint(100, 200)))
os.environ.setdefault('ROS_LOCALHOST_ONLY', '1')
# One OpenMP/MKL thread per worker, and for the processes it starts (nodes, tools), when the workers fill the cores
# (make test: three workers on two cores). Two workers that each run torch with a thread per core wait on each other's
# threads at every parallel region: test_train took 233 s beside a busy core at torch's default, 121 s at one thread.
# A value set by hand is kept; one process (TEST_WORKERS=1) keeps torch's default.
if _WORKER.startswith('gw'):
    _THREADS = max(1, (os.cpu_count() or 1) // max(1, int(os.environ.get('PYTEST_XDIST_WORKER_COUNT', '1') or 1)))
    for _var in ('OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
        os.environ.setdefault(_var, str(_THREADS))
    if 'torch' in sys.modules and os.environ['OMP_NUM_THREADS'].isdigit():   # imported by a plugin: sized already
        sys.modules['torch'].set_num_threads(int(os.environ['OMP_NUM_THREADS']))
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))
os.environ['PYTHONPATH'] = os.pathsep.join(
    [str(REPO)] + [p for p in os.environ.get('PYTHONPATH', '').split(os.pathsep) if p])


def pytest_collection_finish(session):
    """What collection imported (torch, the stream layer, ...) moves to the collector's permanent generation: the
    tests' own garbage collections then walk only what the tests allocate (fork_starts.py does the same for the
    nodes it forks)."""
    import gc
    gc.collect()
    gc.freeze()


def cpu_native_bf16():
    """Whether this CPU has native bfloat16 kernels, from its own flags (Linux /proc/cpuinfo): True with
    AVX512-BF16 or AMX-BF16, False without them (oneDNN's emulation on AVX-512 is slower than float32), None when
    the flags cannot be read."""
    try:
        text = pathlib.Path('/proc/cpuinfo').read_text()
    except OSError:
        return None
    flags = next((set(line.split(':', 1)[1].split()) for line in text.splitlines() if line.startswith('flags')),
                 None)
    if flags is None:
        return None
    return bool(flags & {'avx512_bf16', 'amx_bf16'})


def shared_sequence(name: str) -> pathlib.Path:
    """Path of a sequence in the shared development data folder, or skip the test when the folder is absent."""
    path = SHARED_DATA / name
    if not (path / 'poses.txt').is_file():
        pytest.skip(f'{path} is absent (the shared data folder is only on development machines)')
    return path


@pytest.fixture
def sun3d_frag1() -> pathlib.Path:
    return shared_sequence('sun3d_3dmatch_frag1')


@pytest.fixture
def sun3d_frag2() -> pathlib.Path:
    return shared_sequence('sun3d_3dmatch_frag2')


@pytest.fixture
def tartanair_hospital() -> pathlib.Path:
    return shared_sequence('tartanair_hospital')


@pytest.fixture
def observer():
    """A private rclpy context with one node and an executor, for watching the node under test over DDS."""
    import rclpy
    context = rclpy.context.Context()
    rclpy.init(context=context)
    node = rclpy.create_node('test_observer', context=context)
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(node)
    yield node, executor
    executor.shutdown()
    node.destroy_node()
    rclpy.shutdown(context=context)
