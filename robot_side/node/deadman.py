"""The deadman: the arm stops a fixed time after the operator's newest fresh message.

Counted from that message's send time on our clock (command_gate.py), so a
backlog of old messages cannot extend it; with a roster, from the lease
holder's messages only. The loop wakes at the deadline even with no frame.
"""

from __future__ import annotations

import collections
import logging
from collections import Counter

from robot_side.node.commands.command_gate import CommandGate

log = logging.getLogger(__name__)

#: a deadline that never comes
NEVER_NS = 2**63 - 1


class Deadman:
    """The operator link's state ("ok" or "down") and when silence turns it down."""

    def __init__(self, deadman_ms: float, counters: Counter[str]) -> None:
        self.deadman_ms = deadman_ms
        self.counters = counters
        self.link_state = "down"
        #: (monotonic ns, new state) of the latest link state changes
        self.link_changes: collections.deque[tuple[int, str]] = collections.deque(maxlen=256)

    def deadline_ns(self, gate: CommandGate) -> int:
        """When the operator's silence stops the arm, if nothing fresh is heard before then."""
        heard = gate.last_fresh_ns
        if heard is None or self.link_state != "ok":
            return NEVER_NS
        return heard + round(self.deadman_ms * 1e6) + 1

    def check(self, gate: CommandGate, now: int) -> bool:
        """Update the link state; True when it just tripped (the caller stops the devices)."""
        heard = gate.last_fresh_ns
        fresh = heard is not None and (now - heard) / 1e6 <= self.deadman_ms
        new_state = "ok" if fresh else "down"
        if new_state == self.link_state:
            return False
        log.info("operator link %s -> %s", self.link_state, new_state)
        tripped = new_state == "down" and heard is not None
        if tripped:
            self.counters["deadman_trips"] += 1
        self.link_state = new_state
        self.link_changes.append((now, new_state))
        return tripped
