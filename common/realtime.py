"""Real-time scheduling for the few threads that must run on time, and how late they ran.

The arm's keep-alive kicks the UR controller's watchdog every 20 ms; a kick
150 ms late stops the arm. In the fair scheduler a niceness only ranks a
thread against its neighbours, and a busy PC (a camera, an encoder,
inference, a test suite) can hold it off for hundreds of milliseconds.
``SCHED_FIFO`` puts it ahead of every fair-scheduled thread. Linux keeps a
policy per thread, so only the thread that asks is raised: where the
process may not (no root, no ``LimitRTPRIO=``), the thread runs at the
highest niceness it may, and says so.

``PeriodStats`` keeps the intervals between a periodic thread's wakes, so a
deployment can show how close to its nominal period the keep-alive runs.
"""

from __future__ import annotations

import collections
import contextlib
import os
import threading
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Scheduling:
    """What a thread got: ``fifo`` at ``level`` (its priority), or ``nice`` at ``level``."""

    policy: str
    level: int
    why_not_fifo: str = ""

    @property
    def realtime(self) -> bool:
        return self.policy == "fifo"

    def describe(self) -> str:
        if self.realtime:
            return f"SCHED_FIFO priority {self.level}"
        why = f" (SCHED_FIFO refused: {self.why_not_fifo})" if self.why_not_fifo else ""
        return f"nice {self.level}{why}"


def raise_this_thread(fifo_priority: int, fallback_nice: int) -> Scheduling:
    """This thread at SCHED_FIFO ``fifo_priority`` where granted (0: not asked), else at
    ``fallback_nice`` or the highest niceness it may take."""
    tid = threading.get_native_id()
    why = ""
    if fifo_priority > 0:
        try:
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(fifo_priority))
            return Scheduling("fifo", fifo_priority)
        except (OSError, AttributeError) as e:
            why = getattr(e, "strerror", None) or str(e)
    own = os.getpriority(os.PRIO_PROCESS, tid)
    with contextlib.suppress(OSError):
        os.setpriority(os.PRIO_PROCESS, tid, min(fallback_nice, own))
    return Scheduling("nice", os.getpriority(os.PRIO_PROCESS, tid), why)


class PeriodStats:
    """The intervals between a periodic thread's wakes (the newest ``keep`` of them)."""

    def __init__(self, nominal_s: float, keep: int = 1 << 16) -> None:
        self.nominal_s = nominal_s
        self._intervals: collections.deque[float] = collections.deque(maxlen=keep)
        self._last: float | None = None
        self.count = 0

    def woke(self, now_s: float) -> None:
        if self._last is not None:
            self._intervals.append(now_s - self._last)
            self.count += 1
        self._last = now_s

    def restart(self) -> None:
        """A pause that is not a late wake (a reconnect): the next wake starts a new series."""
        self._last = None

    def summary(self) -> dict[str, float]:
        """p50, p99, p99.9 and max of the period (ms), the nominal and the count; {} when
        there is none yet."""
        if not self._intervals:
            return {}
        ms = np.asarray(self._intervals, dtype=np.float64) * 1000.0
        p50, p99, p999 = np.percentile(ms, (50.0, 99.0, 99.9))
        return {
            "nominal_ms": self.nominal_s * 1000.0,
            "p50_ms": float(p50),
            "p99_ms": float(p99),
            "p999_ms": float(p999),
            "max_ms": float(ms.max()),
            "count": float(self.count),
        }
