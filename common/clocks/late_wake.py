"""A loop that woke long after it was due: its process was starved (or frozen).

Both nodes' loops sleep until their next deadline; a wake ``LATE_WAKE_NS`` or
more after it is no longer jitter but a process the machine did not run, and
nothing the loop does (a stimulus out, the palm's staleness lift) happened
meanwhile. ``LateWakes`` counts them (``late_wakes``, their lateness summed in
``late_wake_ms``) and logs them with when the loop was due and woke, on the
monotonic clock, at most one line per burst (``BurstLog``).
"""

from __future__ import annotations

import logging
from collections import Counter

from common.logs import BurstLog

#: a wake this long after its deadline is a starved process (a loop's deadlines are at most a
#: heartbeat period apart, and anything it waits for wakes it sooner)
LATE_WAKE_NS = 100_000_000


class LateWakes:
    """Counts and logs one loop's late wakes; ``meanwhile`` says what could not happen."""

    def __init__(self, counters: Counter[str], log: logging.Logger, loop: str, meanwhile: str):
        self.counters = counters
        self.meanwhile = meanwhile
        self._log = BurstLog(log, loop)

    def note(self, due_ns: int, woke_ns: int) -> bool:
        """The loop, due at ``due_ns``, woke at ``woke_ns``: True (counted, logged) if late."""
        late = woke_ns - due_ns
        if late <= LATE_WAKE_NS:
            return False
        self.counters["late_wakes"] += 1
        self.counters["late_wake_ms"] += round(late / 1e6)
        self._log(
            f"woke {late / 1e6:.0f} ms after its deadline: the process was starved "
            f"({self.meanwhile}); due_ns={due_ns} woke_ns={woke_ns}"
        )
        return True
