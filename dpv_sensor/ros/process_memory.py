"""Process-wide memory settings of the node (no ROS, no torch): glibc's malloc arenas.

glibc gives every thread that allocates its own malloc arena, up to 8 per core. The node's threads (the
executor, the worker, DDS and the OpenMP pool) then each keep freed memory in their own arena. Under bfloat16
autocast the networks' many short-lived tensors fragment those arenas, and resident memory swung between 0.83
and 1.47 GB over a 30-minute soak. With two arenas the soak medians were 0.76-0.83 GB, against 0.85-0.91 GB
with glibc's default, at the same throughput within the machine's noise; over 25 minutes 0.81 GB in every
window, 0.83 GB p99 (README, Measured numbers).

glibc serves a block above its mmap threshold with a fresh mapping and unmaps it on free, so every use of it
faults its pages in again (zeroed by the kernel). The threshold starts at 128 KiB and rises only when such a
block is freed; which blocks a process happened to free first then decides whether the tensors of a keyframe
(a 32-plane 320x256 DPV is 10 MB, its temporaries up to 21 MB) are mapped anew each time or reused. Two runs of
the same readout differed that way by 1.6 million page faults and 2.5x in time. :func:`pin_mmap_threshold` sets
the threshold where glibc's own rule would end (its largest, 32 MiB, and the trim threshold at twice that), from
the start and for every process the same.
"""
from __future__ import annotations

import ctypes
import os
from typing import Optional, Tuple

M_ARENA_MAX = -8          # glibc <malloc.h>
M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
DEFAULT_ARENAS = 2
MMAP_THRESHOLD_MIB = 32   # glibc's largest (HEAP_MAX_SIZE / 2 on 64-bit); its dynamic threshold stops there too


def _mallopt():
    """glibc's mallopt(param, value) -> 1 on success, or raises OSError / AttributeError."""
    mallopt = ctypes.CDLL(None).mallopt      # the C library already loaded into this process
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    return mallopt


def _apply(what: str, env_keys: Tuple[str, ...], options: Tuple[Tuple[int, int], ...], done: str) -> str:
    """mallopt(parameter, value) for each of `options`, unless one of `env_keys` is set in the environment (glibc
    has applied it already, and it wins). Returns '<what>: ...' saying what is in force; never raises."""
    env = [k for k in env_keys if os.environ.get(k)]
    if env:
        return f'{what}: {", ".join(f"{k}={os.environ[k]}" for k in env)} from the environment'
    try:
        mallopt = _mallopt()
    except (OSError, AttributeError) as exc:
        return f'{what}: left as glibc has it (no mallopt: {exc})'
    if not all(mallopt(param, int(value)) == 1 for param, value in options):
        return f'{what}: left as glibc has it (mallopt refused)'
    return f'{what}: {done}'


def limit_malloc_arenas(n: int = DEFAULT_ARENAS) -> str:
    """Cap glibc's malloc arenas at `n` for threads created from now on; call it before the process starts
    threads. A `MALLOC_ARENA_MAX` in the environment wins. Returns a line for the log saying what is in force."""
    return _apply('malloc arenas', ('MALLOC_ARENA_MAX',), ((M_ARENA_MAX, n),),
                  f'at most {int(n)} (set MALLOC_ARENA_MAX to override)')


def pin_mmap_threshold(mib: int = MMAP_THRESHOLD_MIB) -> str:
    """Blocks up to `mib` MiB come from the heap and are reused after free (module docstring); the heap's top is
    returned to the system beyond twice that. A `MALLOC_MMAP_THRESHOLD_` or `MALLOC_TRIM_THRESHOLD_` in the
    environment wins. Returns a line for the log."""
    size = int(mib) << 20
    return _apply('malloc mmap threshold', ('MALLOC_MMAP_THRESHOLD_', 'MALLOC_TRIM_THRESHOLD_'),
                  ((M_MMAP_THRESHOLD, size), (M_TRIM_THRESHOLD, 2 * size)),
                  f'{int(mib)} MiB, trim above {2 * int(mib)} MiB (MALLOC_MMAP_THRESHOLD_ overrides)')


def configure_malloc() -> str:
    """The node's malloc settings (:func:`limit_malloc_arenas`, :func:`pin_mmap_threshold`), before any thread
    exists; returns the line the node logs."""
    return f'{limit_malloc_arenas()}; {pin_mmap_threshold()}'


def proc_status_kib(pid: int | str, key: str) -> Optional[int]:
    """A field of /proc/<pid>/status in kB (e.g. VmRSS, VmHWM; pid 'self' for this process), or None."""
    try:
        with open(f'/proc/{pid}/status') as f:
            for line in f:
                if line.startswith(key + ':'):
                    return int(line.split()[1])
    except OSError:
        return None
    return None
