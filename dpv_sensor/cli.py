"""Argument groups the command-line tools share, built from the settings table (``dpv_sensor.params``).

``add_setting(parser, name)`` declares ``--name-with-dashes`` with the setting's default, type, choices and
description; ``add_config(parser)`` declares the ``--config KEY=VALUE ...`` list every tool that runs the estimator
takes (parsed with ``params.parse_assignments``). No tool re-declares a setting's default or choices.
"""
from __future__ import annotations

import argparse

from dpv_sensor import params as P

__all__ = ['add_setting', 'add_config']


def add_setting(parser, name: str, flag: str | None = None, **overrides) -> argparse.Action:
    """``--<name>`` for one setting of the table (``overrides``: other argparse keywords, e.g. a tool's own
    default)."""
    s = P.spec(name)
    kw = dict(dest=name, default=s.fresh_default(), help=s.description + ' (default: %(default)s)')
    if s.choices:
        kw['choices'] = tuple(s.choices)
    if s.kind in (int, float):
        kw['type'] = s.kind
    kw.update(overrides)
    return parser.add_argument(flag or '--' + name.replace('_', '-'), **kw)


def add_config(parser, help_extra: str = '') -> argparse.Action:
    """``--config KEY=VALUE ...``: settings of the table by name (config/dpv_sensor.yaml names)."""
    return parser.add_argument('--config', nargs='*', default=[], metavar='KEY=VALUE',
                               help="settings by name (config/dpv_sensor.yaml names and the estimator's "
                                    'library settings), e.g. filter_mode=global processing_width=160' + help_extra)


def tool_argv(argv=None) -> list:
    """The tool's own arguments: `ros2 run` may append `--ros-args ...`, which the console tools do not use."""
    import sys
    argv = list(sys.argv[1:] if argv is None else argv)
    return argv[:argv.index('--ros-args')] if '--ros-args' in argv else argv
