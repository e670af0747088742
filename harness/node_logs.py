"""A node's log lines read back (``deepxpalm -v`` writes them), with their times on this clock."""

from __future__ import annotations

import re
import time
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class LogLine:
    """One line of the node's log: wall time (``time.time()``, ms resolution), level, logger."""

    created: float
    level: str
    name: str
    message: str


_LOG_LINE = re.compile(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d),(\d{3}) (\w+) ([\w.]+): (.*)$")


def read_log_lines(path: Path, name: str = "") -> list[LogLine]:
    """A node's log lines (``deepxpalm -v``) from loggers under ``name``, times on this clock."""
    out = []
    for line in path.read_text(errors="replace").splitlines():
        m = _LOG_LINE.match(line)
        if m is None or not m[4].startswith(name):
            continue  # a traceback's continuation, a stack dump
        stamp = time.mktime(time.strptime(m[1], "%Y-%m-%d %H:%M:%S"))
        out.append(LogLine(stamp + int(m[2]) / 1000, m[3], m[4], m[5]))
    return out
