"""Clocks and deadline pacing.

All timestamps in this project come from the monotonic clock in
nanoseconds: it never jumps, and the cross-machine offset between two
monotonic clocks is estimated from heartbeat round trips, never assumed.
"""

from __future__ import annotations

import time
from collections.abc import Callable

now_ns = time.monotonic_ns

#: what a node reads the time from: ``now_ns`` when it runs, a ``VirtualClock`` in a replay
Clock = Callable[[], int]


def wall_offset_ns(tries: int = 5) -> int:
    """The wall clock minus the monotonic clock, from the tightest of ``tries`` brackets
    (monotonic, wall, monotonic): a preemption between two plain reads adds itself to every
    time converted with the offset (3 ms seen on a busy machine)."""
    best_span, best = None, 0
    for _ in range(tries):
        m0 = time.monotonic_ns()
        wall = time.time_ns()
        m1 = time.monotonic_ns()
        if best_span is None or m1 - m0 < best_span:
            best_span, best = m1 - m0, wall - (m0 + m1) // 2
    return best


def now_s() -> float:
    return time.monotonic()


class VirtualClock:
    """A clock that moves only when told: replays and benches run a node in recorded time.

    A node handed one reads it wherever it would read ``now_ns``, so its
    stale-frame check, keyframes and timestamps follow the replayed times, and
    a 27 s scene costs what its frames cost.
    """

    def __init__(self, t_ns: int = 1_000_000_000) -> None:
        self.t_ns = t_ns

    def __call__(self) -> int:
        return self.t_ns

    def advance(self, ns: int) -> int:
        """Move the clock on by ``ns``; the new time."""
        self.t_ns += ns
        return self.t_ns


class Rate:
    """Paces a loop against absolute deadlines (ur_rtde's initPeriod/waitPeriod).

    A late cycle does not shift the schedule: missed deadlines are skipped and
    counted in ``overruns``, so a stall never turns into a burst of catch-up
    cycles.
    """

    def __init__(self, hz: float) -> None:
        if not hz > 0:
            raise ValueError(f"rate must be positive, not {hz!r}")
        self.period_ns = round(1e9 / hz)
        self.next_deadline_ns = now_ns() + self.period_ns
        self.overruns = 0

    def remaining_s(self) -> float:
        return max(0.0, (self.next_deadline_ns - now_ns()) / 1e9)

    def due(self) -> bool:
        return now_ns() >= self.next_deadline_ns

    def advance(self) -> None:
        """Move to the next deadline after now, counting any that were missed."""
        now = now_ns()
        self.next_deadline_ns += self.period_ns
        if now >= self.next_deadline_ns:
            missed = (now - self.next_deadline_ns) // self.period_ns + 1
            self.overruns += int(missed)
            self.next_deadline_ns += int(missed) * self.period_ns

    def restart(self) -> None:
        """The next deadline is one period from now (an event-driven cycle just ran)."""
        self.next_deadline_ns = now_ns() + self.period_ns

    def sleep(self) -> None:
        """Sleep until the current deadline, then advance to the next one."""
        remaining = self.remaining_s()
        if remaining > 0:
            time.sleep(remaining)
        self.advance()


class Periodic:
    """A duty due once per period that may run up to ``early_s`` before its deadline.

    A node that is awake anyway (a frame, a message) does the duty then
    instead of waking again for it a few milliseconds later: a wake-up costs
    50-90 us of CPU on a virtual machine. Deadlines stay on a fixed grid, so
    the average rate is exact and an interval is never longer than one
    period plus ``early_s``.
    """

    def __init__(self, hz: float, early_s: float, start_ns: int | None = None) -> None:
        if not hz > 0:
            raise ValueError(f"rate must be positive, not {hz!r}")
        self.period_ns = round(1e9 / hz)
        if not 0 <= early_s * 1e9 < self.period_ns:
            raise ValueError(f"early_s must be in [0, one period), not {early_s!r}")
        self.early_ns = round(early_s * 1e9)
        #: the latest time the duty may run: a sleeping loop wakes for it then
        self.deadline_ns = now_ns() if start_ns is None else start_ns

    def due(self, now: int) -> bool:
        return now >= self.deadline_ns - self.early_ns

    def done(self, now: int) -> None:
        """The duty ran at ``now``: the next deadline is one period on, or from now if behind."""
        self.deadline_ns += self.period_ns
        if self.due(now):  # more than a period late (a stall): no burst of catch-ups
            self.deadline_ns = now + self.period_ns
