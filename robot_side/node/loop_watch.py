"""The frame loop's own timing, so a gap in the stimuli says where it came from.

Two different causes leave the operator without a fresh stimulus: the loop
was not run (the process starved: it woke long after its deadline) or it ran
and spent its turn somewhere (a phase took long). ``LoopWatch`` counts and
logs each (``late_wakes`` and ``slow_turns``, with their milliseconds), a
slow turn with the time of each phase. Its cost is a clock read per phase.
"""

from __future__ import annotations

import itertools
import logging
from collections import Counter

from common.clocks.clock import now_ns
from common.clocks.late_wake import LateWakes
from common.logs import BurstLog

log = logging.getLogger(__name__)

#: a turn this long delays the next stimulus past half the operator's staleness limit
SLOW_TURN_NS = 75_000_000


class LoopWatch:
    """Counts and logs the frame loop's late wakes and slow turns."""

    def __init__(self, counters: Counter[str]) -> None:
        self.counters = counters
        self._marks: list[tuple[str, int]] = []
        self._late = LateWakes(
            counters, log, "the frame loop",
            "no stimulus meanwhile; the operator's palm lifts past its staleness limit",
        )  # fmt: skip
        self._slow = BurstLog(log, "the frame loop")

    def woke(self, due_ns: int, woke_ns: int) -> None:
        """The loop's wait for ``due_ns`` returned at ``woke_ns``; a turn starts."""
        self._marks = [("wake", woke_ns)]
        self._late.note(due_ns, woke_ns)

    def mark(self, phase: str) -> None:
        """The phase ``phase`` of this turn ended now."""
        self._marks.append((phase, now_ns()))

    def turn_done(self, last_phase: str) -> None:
        """The turn's last phase, ``last_phase``, ended now: log the turn if it was slow."""
        self.mark(last_phase)
        marks = self._marks
        if len(marks) < 2:
            return
        took = marks[-1][1] - marks[0][1]
        if took <= SLOW_TURN_NS:
            return
        self.counters["slow_turns"] += 1
        self.counters["slow_turn_ms"] += round(took / 1e6)
        phases = ", ".join(
            f"{name} {(t - t0) / 1e6:.0f} ms" for (_, t0), (name, t) in itertools.pairwise(marks)
        )
        self._slow(f"a turn took {took / 1e6:.0f} ms ({phases})")
