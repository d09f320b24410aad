"""Helpers the tools share for running the node as a child process and reading its memory from /proc."""
from __future__ import annotations

import sys
from typing import Any, Dict, List, Optional


def node_command(params: Dict[str, Any], remaps: Dict[str, str]) -> List[str]:
    """`python -m dpv_sensor.node --ros-args -p k:=v ... -r a:=b ...` for these parameters and remaps."""
    cmd = [sys.executable, '-m', 'dpv_sensor.node', '--ros-args']
    for k, v in params.items():
        if isinstance(v, bool):
            v = 'true' if v else 'false'
        elif isinstance(v, (list, tuple)):
            v = '[' + ','.join(repr(float(x)) for x in v) + ']'
        elif isinstance(v, str) and v == '':
            v = "''"
        cmd += ['-p', f'{k}:={v}']
    for a, b in remaps.items():
        cmd += ['-r', f'{a}:={b}']
    return cmd


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
