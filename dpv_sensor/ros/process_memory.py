"""Process-wide memory settings of the node (no ROS, no torch): glibc's malloc arenas.

glibc gives every thread that allocates its own malloc arena, up to 8 per core. The node's threads (the
executor, the worker, DDS and the OpenMP pool) then each keep freed memory in their own arena. Under bfloat16
autocast the networks' many short-lived tensors fragment those arenas, and resident memory swung between 0.83
and 1.47 GB over a 30-minute soak. With two arenas the soak medians were 0.76-0.83 GB, against 0.85-0.91 GB
with glibc's default, at the same throughput within the machine's noise; over 25 minutes 0.81 GB in every
window, 0.83 GB p99 (README, Measured numbers).
"""
from __future__ import annotations

import ctypes
import os
from typing import Optional

M_ARENA_MAX = -8          # glibc <malloc.h>
DEFAULT_ARENAS = 2


def limit_malloc_arenas(n: int = DEFAULT_ARENAS) -> str:
    """Cap glibc's malloc arenas at `n` for threads created from now on; call it before the process starts
    threads. A `MALLOC_ARENA_MAX` in the environment wins (glibc has already applied it). Returns a line for the
    log saying what is in force. Never raises: on a C library without `mallopt` nothing changes."""
    env = os.environ.get('MALLOC_ARENA_MAX')
    if env:
        return f'malloc arenas: {env} (MALLOC_ARENA_MAX from the environment)'
    try:
        mallopt = ctypes.CDLL(None).mallopt      # the C library already loaded into this process
    except (OSError, AttributeError) as exc:
        return f'malloc arenas: left as they are (no glibc mallopt: {exc})'
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    if mallopt(M_ARENA_MAX, int(n)) != 1:
        return 'malloc arenas: left as they are (mallopt(M_ARENA_MAX) refused)'
    return f'malloc arenas: at most {int(n)} (set MALLOC_ARENA_MAX to override)'


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
