"""Small helpers every layer may use (no ROS, no torch import): the one JSON sanitiser and the one code version."""
from __future__ import annotations

import math
import pathlib
import subprocess

import numpy as np

__all__ = ['to_jsonable', 'code_version']

REPO = pathlib.Path(__file__).resolve().parents[1]


def to_jsonable(obj):
    """Strict JSON, recursively: numpy scalars/arrays and tensors -> Python (a one-element tensor -> its number),
    NaN/inf -> None, tuples -> lists, paths -> str, dict keys -> str."""
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return to_jsonable(obj.item())
    if type(obj).__module__ == 'torch' and hasattr(obj, 'numel'):       # a torch.Tensor, without importing torch
        return to_jsonable(obj.item() if obj.numel() == 1 else obj.tolist())
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, pathlib.PurePath):
        return str(obj)
    return obj


def code_version() -> str:
    """``dpv_sensor.__version__`` plus ``+g<short hash>`` (and ``.dirty``) when inside a git checkout."""
    from dpv_sensor import __version__
    try:
        h = subprocess.run(['git', '-C', str(REPO), 'rev-parse', '--short', 'HEAD'], capture_output=True,
                           text=True, timeout=5)
        if h.returncode != 0 or not h.stdout.strip():
            return __version__
        d = subprocess.run(['git', '-C', str(REPO), 'status', '--porcelain', '--untracked-files=no'],
                           capture_output=True, text=True, timeout=5)
        dirty = '.dirty' if d.returncode == 0 and d.stdout.strip() else ''
        return f'{__version__}+g{h.stdout.strip()}{dirty}'
    except (OSError, subprocess.SubprocessError):
        return __version__
