"""Clocks and deadline pacing.

All timestamps in this project come from the monotonic clock in
nanoseconds: it never jumps, and the cross-machine offset between two
monotonic clocks is estimated from heartbeat round trips, never assumed.
"""

from __future__ import annotations

import time

now_ns = time.monotonic_ns


def now_s() -> float:
    return time.monotonic()


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
