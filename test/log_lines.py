"""A logger stand-in that keeps what the code under test logs, as (level, message) pairs."""
from __future__ import annotations


class Lines:
    def __init__(self):
        self.lines: list[tuple[str, str]] = []

    def info(self, m):
        self.lines.append(('info', m))

    def warning(self, m):
        self.lines.append(('warn', m))

    def error(self, m):
        self.lines.append(('error', m))
