"""``arm_stop``\\ s the replay window cannot yet believe: the arm stops now, the latch waits.

A stop from a sender that has not yet proven it hears this robot run
(command_gate.py, ``PENDING``) might be a replay of an older run's stop.
Refusing it would ignore a real STOP pressed before the operator heard the
robot; latching it would let a replay hold the arm. So the arm stops at
once and holds still (``StopLatch.pending``) while the stop waits: it
latches when its sender proves live, is refused when it was sent before
this run or its sender stays silent for 2 s, and the holder's
``arm_resume`` releases it as it releases a latched one.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable

from common.wire.messages import Command
from robot_side.node.commands.command_gate import (
    PENDING,
    STOP_BEFORE_RUN,
    STOP_PROVEN,
    STOP_UNPROVEN,
    RobotRun,
)
from robot_side.node.commands.lease import Peer
from robot_side.node.commands.stop_latch import REFUSALS
from robot_side.node.handover import Handover

log = logging.getLogger(__name__)

#: what the log says of a pending stop's outcome
_OUTCOMES = {
    STOP_PROVEN: "its sender proved it hears this run: latched",
    STOP_BEFORE_RUN: "sent before this robot run started (a replay): refused, nothing latched",
    STOP_UNPROVEN: "its sender never proved it hears this run within 2 s (a replay, or an "
    "operator that cannot hear this robot): refused, nothing latched",
}


class PendingStops:
    """The stops awaiting their sender's proof, and what becomes of each."""

    def __init__(
        self,
        handover: Handover,
        run: RobotRun,
        *,
        counters: Counter[str],
        announce: Callable[[], None],
    ) -> None:
        """``announce`` asks for a heartbeat at once (the latch changed)."""
        self.handover = handover
        self.run = run
        self.counters = counters
        self.announce = announce
        #: (signer, its state, the stop, arrival)
        self.waiting: list[tuple[bytes | None, Peer, Command, int]] = []

    def __len__(self) -> int:
        return len(self.waiting)

    def pend(self, key: bytes | None, peer: Peer, msg: Command, t_recv: int, holder: bool) -> bool:
        """Hold a stop until its sender's proof; True when the arm is to stop now.

        Its sender's role is judged now (a recorder's stop moves nothing);
        while it waits, nothing sets the arm moving (``StopLatch.pending``).
        The same stop twice waits once.
        """
        latch = self.handover.stop_latch
        refusal = latch.judge("arm_stop", holder, peer.entry.role)
        if refusal is not None:
            self.counters[refusal] += 1
            self.handover.record(msg, f"refused: {REFUSALS[refusal]}")
            return False
        for k, _, other, _ in self.waiting:
            if k == key and (other.session, other.seq) == (msg.session, msg.seq):
                self.counters["commands_replayed"] += 1
                return False
        self.counters[PENDING] += 1
        self.waiting.append((key, peer, msg, t_recv))
        latch.pending = len(self.waiting)
        log.warning(
            "arm_stop from %s (boot %016x, seq %d) stopped the arm; it latches once its "
            "sender proves it hears this run",
            peer.entry.name,
            msg.session or 0,
            msg.seq,
        )
        return True

    def judge(self, now: int) -> None:
        """Latch each pending stop whose sender proved live, refuse those that cannot be."""
        waiting = []
        for key, peer, msg, t_recv in self.waiting:
            outcome = peer.gate.judge_pending(msg, t_recv, now, self.run)
            if outcome is None:
                waiting.append((key, peer, msg, t_recv))
                continue
            self.counters[outcome] += 1
            log.warning(
                "pending arm_stop from %s (boot %016x, seq %d): %s",
                peer.entry.name,
                msg.session or 0,
                msg.seq,
                _OUTCOMES[outcome],
            )
            if outcome == STOP_PROVEN:
                if self.handover.stop_latch.apply("arm_stop", peer.entry.name, now):
                    self.announce()
                self.counters["arm_stops_latched"] += 1
            else:
                self.handover.record(msg, f"refused: {outcome}")
        self.waiting = waiting
        self.handover.stop_latch.pending = len(waiting)

    def release(self, who: str) -> None:
        """The holder resumed after those stops were pressed: as it releases a latched one."""
        if not self.waiting:
            return
        self.counters["arm_stops_pending_resumed"] += len(self.waiting)
        log.warning("%d pending arm_stop(s) released by %s's arm_resume", len(self.waiting), who)
        self.waiting = []
        self.handover.stop_latch.pending = 0
