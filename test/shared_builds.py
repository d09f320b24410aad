"""What several test files build alike, built once per test run: the first pytest worker that needs it builds it
under a lock in the run's temp folder (all workers of a run share its parent), the others wait for it and use it.

    adapt_recording(tmp_path_factory)    a rendered 90-frame recording of a small room at 160x128, with and without
                                         depth/, and the adapt tool's output on the one without (test_adapt.py,
                                         test_node_adapted_weights.py)
"""
from __future__ import annotations

import fcntl
import os
import pathlib
import shutil
from typing import Callable, NamedTuple

W, H = 160, 128
# a room 2-2.8 m across: the shipped weights were trained in rooms of 3-7.5 m
SMALL_ROOM = {'room_size_x': (2.0, 2.8), 'room_size_y': (2.0, 2.8), 'room_height': (2.2, 2.4)}
# the adapt tool at the tests' size, a few steps
ADAPT_FAST = ['--width', str(W), '--height', str(H), '--threads', '1', '--quiet', '--holdout', '0.35', '--unroll',
              '1', '--steps', '4', '--lr', '1e-3']


def build_once(tmp_path_factory, name: str, build: Callable[[pathlib.Path], None]) -> pathlib.Path:
    """The folder `name` of this run, built by `build(folder)` the first time any worker asks for it. A build that
    failed leaves no mark of completion: the next one to ask builds it again (and fails the same way)."""
    base = tmp_path_factory.getbasetemp()
    root = (base.parent if os.environ.get('PYTEST_XDIST_WORKER') else base) / 'built_once'
    root.mkdir(exist_ok=True)
    folder, done = root / name, root / f'{name}.done'
    with open(root / f'{name}.lock', 'w') as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not done.exists():
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
            build(folder)
            done.touch()
    return folder


class AdaptRecording(NamedTuple):
    with_depth: pathlib.Path
    without_depth: pathlib.Path
    adapted: pathlib.Path          # the tool's --out on without_depth with ADAPT_FAST
    code: int                      # its exit code


def adapt_recording(tmp_path_factory) -> AdaptRecording:
    def build(folder: pathlib.Path) -> None:
        from dpv_sensor.data.sequence import write_sequence
        from dpv_sensor.data.synthetic import render_sequence
        from dpv_sensor.tools import adapt as tool
        with_depth = write_sequence(folder / 'with_depth', render_sequence(65, 90, width=W, height=H, **SMALL_ROOM),
                                    lossless=True)
        shutil.copytree(with_depth, folder / 'without_depth')
        shutil.rmtree(folder / 'without_depth' / 'depth')
        code = tool.main([str(folder / 'without_depth'), '--out', str(folder / 'adapted'), *ADAPT_FAST])
        (folder / 'code').write_text(str(code))

    folder = build_once(tmp_path_factory, 'adapt_recording', build)
    return AdaptRecording(folder / 'with_depth', folder / 'without_depth', folder / 'adapted',
                          int((folder / 'code').read_text()))
