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

import contextlib
import logging
import os
import threading
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)

#: numpy's BLAS and OpenMP pools at one thread (none of their own), for a child's environment
#: (they read it once, at numpy's import). A pool thread waits for work by spinning: in a
#: process raised to SCHED_FIFO that holds a core (the arm process), and beside a benchmark's
#: timed work it is noise
ONE_THREAD_POOLS = {
    "OMP_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "NUMEXPR_NUM_THREADS": "1",
}


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


def realtime_scheduling(tid: int) -> tuple[int, os.sched_param] | None:
    """Thread ``tid``'s real-time policy and its parameters, to set back later; None when it
    runs in the fair scheduler (or its scheduling cannot be read)."""
    try:
        policy = os.sched_getscheduler(tid)
        if policy not in (getattr(os, "SCHED_FIFO", None), getattr(os, "SCHED_RR", None)):
            return None
        return policy, os.sched_getparam(tid)
    except (OSError, AttributeError):
        return None


def restore_scheduling(tid: int, scheduling: tuple[int, os.sched_param], what: str) -> None:
    """Thread ``tid`` back at the real-time ``scheduling`` it had (``realtime_scheduling``);
    a grant withdrawn meanwhile leaves it fair, and is said."""
    try:
        os.sched_setscheduler(tid, *scheduling)
    except OSError as e:
        log.warning("%s: SCHED_FIFO not restored (%s): it runs at its niceness", what, e)


@contextlib.contextmanager
def fair_while(what: str):
    """This thread in the fair scheduler for the block, then at its real-time priority again.

    For a call that may busy-wait on another process (ur-rtde's ``sendCommand`` spins
    until the controller says it is ready): spun at ``SCHED_FIFO`` it holds a core from
    every fair thread, the other process's included. A thread that is not real-time, or
    may not be again (logged), is left as it was.
    """
    tid = threading.get_native_id()
    scheduling = realtime_scheduling(tid)
    if scheduling is None:
        yield
        return
    os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
    try:
        yield
    finally:
        restore_scheduling(tid, scheduling, what)


#: the period histogram's resolution and range: a period longer than the range counts in the
#: last bin (its exact length is kept as the max)
BIN_S = 50e-6
RANGE_S = 0.5


class PeriodStats:
    """The intervals between a periodic thread's wakes, as a histogram (50 us bins).

    A wake costs an increment; a summary a cumulative sum over the bins: neither
    holds the interpreter lock long enough to delay the thread it measures (a
    percentile over the last 65,536 intervals held it 5 ms).
    """

    def __init__(self, nominal_s: float) -> None:
        self.nominal_s = nominal_s
        self._bins = np.zeros(int(RANGE_S / BIN_S) + 1, dtype=np.int64)
        self._last: float | None = None
        self._max_s = 0.0
        self.count = 0

    def woke(self, now_s: float) -> None:
        last, self._last = self._last, now_s
        if last is None:
            return
        interval = now_s - last
        self._bins[min(int(interval / BIN_S), len(self._bins) - 1)] += 1
        self._max_s = max(self._max_s, interval)
        self.count += 1

    def restart(self) -> None:
        """A pause that is not a late wake (a reconnect): the next wake starts a new series."""
        self._last = None

    def clear(self) -> None:
        """Forget every interval so far (a new connection's series starts)."""
        self._bins[:] = 0
        self._max_s, self.count, self._last = 0.0, 0, None

    def summary(self) -> dict[str, float]:
        """p50, p99, p99.9 and max of the period (ms, to the bin's upper edge), the nominal and
        the count; {} when there is none yet."""
        if not self.count:
            return {}
        cumulative = np.cumsum(self._bins)

        def at(q: float) -> float:
            index = int(np.searchsorted(cumulative, q * self.count, side="left"))
            return min((index + 1) * BIN_S, self._max_s) * 1000.0

        return {
            "nominal_ms": self.nominal_s * 1000.0,
            "p50_ms": at(0.5),
            "p99_ms": at(0.99),
            "p999_ms": at(0.999),
            "max_ms": self._max_s * 1000.0,
            "count": float(self.count),
        }
