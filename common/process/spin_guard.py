"""A real-time thread's call that may busy-wait, put back in the fair scheduler if it does.

ur-rtde sends a command (a watchdog kick too) only once its control script
says "ready", and waits for that in a loop with no sleep, up to its 3 s
timeout. A kick or a jog normally returns within a millisecond; one that
meets a script which will never say ready (stopped on the pendant in the few
milliseconds before the stream shows it, a starved controller) spins. At
``SCHED_FIFO`` that spin holds a whole core from every fair thread of the
machine, the controller's simulator and the robot node included, for as long
as it lasts.

``SpinGuard`` bounds it: the calling thread marks the call (``watched``),
another thread that wakes regularly (the arm's deadman) calls ``check``, and
a call still running after ``limit_s`` has its thread moved to the fair
scheduler (its niceness unchanged) until it returns, then raised again. The
spin still ends only at ur-rtde's timeout, but it shares the CPU like any
other work. The checker must be able to run while the call spins: ur-rtde
releases the interpreter lock in its calls, and on one core the checker
needs a priority above the spinning thread (Linux's real-time throttling
otherwise lets it run only in the last 5 % of each second).
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
from collections.abc import Iterator
from dataclasses import dataclass

from common.clocks.clock import now_s
from common.process.realtime import realtime_scheduling, restore_scheduling

log = logging.getLogger(__name__)


@dataclass
class _Call:
    tid: int
    what: str
    started: float
    #: the real-time scheduling its thread had when a check moved it (None: not moved)
    moved_from: tuple[int, os.sched_param] | None = None


class SpinGuard:
    """Calls on real-time threads that must return within ``limit_s`` or lose their priority."""

    def __init__(self, limit_s: float) -> None:
        self.limit_s = limit_s
        self.demotions = 0  # calls moved to the fair scheduler, since construction
        self._lock = threading.Lock()
        self._calls: dict[int, _Call] = {}  # the watched calls, by thread (a kick, a jog)

    @contextlib.contextmanager
    def watched(self, what: str) -> Iterator[None]:
        """The block is one call on this thread (one at a time per thread: a kick and a jog on
        two threads are watched each on its own). No system call here: the scheduling is read
        only by a check that finds the call late, and a fair thread is left as it is."""
        tid = threading.get_native_id()
        with self._lock:
            self._calls[tid] = _Call(tid, what, now_s())
        try:
            yield
        finally:
            with self._lock:
                call = self._calls.pop(tid, None)
            if call is not None and call.moved_from is not None:
                restore_scheduling(tid, call.moved_from, what)

    def check(self) -> bool:
        """From another thread: watched calls running past ``limit_s`` on a real-time thread
        go fair (each once); True when this check moved one."""
        now, moved = now_s(), []
        with self._lock:
            for call in self._calls.values():
                if call.moved_from is not None or now - call.started <= self.limit_s:
                    continue
                scheduling = realtime_scheduling(call.tid)
                if scheduling is None:  # fair already (or gone): nothing to move
                    continue
                try:
                    os.sched_setscheduler(call.tid, os.SCHED_OTHER, os.sched_param(0))
                except OSError:  # the thread ended, or the right to change it is gone
                    continue
                call.moved_from = scheduling
                self.demotions += 1
                moved.append(call)
        for call in moved:
            log.warning(
                "%s has not returned after %.0f ms (it waits in a loop without sleeping for a "
                "controller that does not answer): moved to the fair scheduler until it returns",
                call.what,
                (now - call.started) * 1000,
            )
        return bool(moved)
