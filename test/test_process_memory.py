"""The node's malloc settings: glibc's arenas capped (threads started afterwards share them instead of making one
each) and its mmap threshold pinned (tensor-sized blocks come from the heap and are reused)."""
import os
import subprocess
import sys

import pytest

from dpv_sensor.ros.process_memory import limit_malloc_arenas

_COUNT_ARENAS = r"""
import ctypes, sys, threading
sys.path.insert(0, {repo!r})
from dpv_sensor.ros.process_memory import limit_malloc_arenas
if {limit}:
    print(limit_malloc_arenas(2), file=sys.stderr)
libc = ctypes.CDLL('libc.so.6')
libc.malloc.restype = ctypes.c_void_p
libc.free.argtypes = (ctypes.c_void_p,)
barrier = threading.Barrier(8)
def work():
    barrier.wait()                         # all eight threads alive at once: none can inherit a freed arena
    for _ in range(200):
        libc.free(libc.malloc(64 * 1024))
ts = [threading.Thread(target=work) for _ in range(8)]
[t.start() for t in ts]; [t.join() for t in ts]
libc.malloc_stats()                        # writes 'Arena N:' per arena to stderr
"""


def _arenas(limit: bool, env_extra=None) -> tuple[int, str]:
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = {k: v for k, v in os.environ.items() if k != 'MALLOC_ARENA_MAX'}
    env.update(env_extra or {})
    out = subprocess.run([sys.executable, '-c', _COUNT_ARENAS.format(repo=repo, limit=limit)], env=env,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    return sum(1 for line in out.stderr.splitlines() if line.startswith('Arena ')), out.stderr


@pytest.mark.skipif(not sys.platform.startswith('linux'), reason='glibc malloc')
def test_arena_cap_holds_for_threads_started_afterwards():
    free, _ = _arenas(limit=False)
    capped, log = _arenas(limit=True)
    assert free > 2, f'without the cap eight threads should get arenas of their own (got {free})'
    assert capped <= 2, log
    assert 'at most 2' in log


def test_environment_setting_wins(monkeypatch):
    monkeypatch.setenv('MALLOC_ARENA_MAX', '4')
    assert limit_malloc_arenas(2) == 'malloc arenas: MALLOC_ARENA_MAX=4 from the environment'


_MAPPED_BLOCKS = r"""
import ctypes, sys
sys.path.insert(0, {repo!r})
from dpv_sensor.ros.process_memory import pin_mmap_threshold
if {pin}:
    print(pin_mmap_threshold(), file=sys.stderr)
libc = ctypes.CDLL('libc.so.6')
libc.malloc.restype = ctypes.c_void_p
libc.free.argtypes = (ctypes.c_void_p,)
class Info(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ('arena', 'ordblks', 'smblks', 'hblks', 'hblkhd', 'usmblks',
                                                'fsmblks', 'uordblks', 'fordblks', 'keepcost')]
libc.mallinfo2.restype = Info
before = libc.mallinfo2().hblks          # blocks served by a mapping of their own
block = libc.malloc(16 << 20)            # a 16 MiB tensor's worth
print(libc.mallinfo2().hblks - before)
libc.free(block)
"""


def _mapped_blocks(pin: bool) -> tuple[int, str]:
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = {k: v for k, v in os.environ.items() if not k.startswith('MALLOC_')}
    out = subprocess.run([sys.executable, '-c', _MAPPED_BLOCKS.format(repo=repo, pin=pin)], env=env,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    return int(out.stdout.split()[-1]), out.stderr


@pytest.mark.skipif(not sys.platform.startswith('linux'), reason='glibc malloc')
def test_pinned_threshold_serves_a_16_mib_block_from_the_heap():
    # glibc's starting threshold (128 KiB) maps a 16 MiB block of its own, which is unmapped on free and faulted
    # in again on the next use; pinned at 32 MiB it comes from the heap and is reused
    mapped_default, _ = _mapped_blocks(pin=False)
    mapped_pinned, log = _mapped_blocks(pin=True)
    assert mapped_default == 1
    assert mapped_pinned == 0, log
    assert 'malloc mmap threshold: 32 MiB, trim above 64 MiB' in log


def test_environment_threshold_wins(monkeypatch):
    from dpv_sensor.ros.process_memory import pin_mmap_threshold
    monkeypatch.setenv('MALLOC_MMAP_THRESHOLD_', '1048576')
    assert pin_mmap_threshold() == 'malloc mmap threshold: MALLOC_MMAP_THRESHOLD_=1048576 from the environment'
