"""The control lease: which one operator key a robot acts on, and how it changes hands.

Several operators see one robot through the router; exactly one of them may
command it at a time. Every operator message is signed (common/wire/signing.py)
and its signer looked up in the robot's own roster (common/keys/roster.py):

- a key not in the roster is ignored, whatever the router let through;
- only ``controller`` keys may ask for the lease (``lease_request``); the
  first to ask while nobody holds it gets it;
- a request while someone holds it waits for the holder: ``lease_grant``
  (to the requester, or any controller key) hands it over at once,
  ``lease_release`` gives it up (to a waiting requester, if any). A request
  nobody grants lapses after ``request_timeout_ns``;
- the holder's silence ends the lease: the robot's deadman (counted from
  the holder's newest fresh message only) stops the arm and the lease
  expires; a waiting requester then gets it.

Each operator key has its own clock-offset estimate and its own command
gate (freshness, replay window): five operators' heartbeats are five clocks.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

from common.clocks.clock_sync import ClockSync
from common.keys.roster import OperatorEntry
from common.wire.messages import Command
from robot_side.node.commands.command_gate import CommandGate

log = logging.getLogger(__name__)

#: Outcomes of a lease action, each the name of the counter it increments.
GRANTED = "lease_granted"
HANDED_OVER = "lease_handed_over"
PENDING = "lease_pending"
HELD = "lease_already_held"
RELEASED = "lease_released"
REFUSED_ROLE = "lease_refused_role"
REFUSED_NOT_HOLDER = "lease_refused_not_holder"
REFUSED_GRANTEE = "lease_refused_grantee"
REFUSED_SILENT = "lease_refused_grantee_silent"
TIMED_OUT = "lease_requests_timed_out"
EXPIRED = "lease_expired"


@dataclass
class Peer:
    """One operator key: who it is, its clock and its command gate."""

    entry: OperatorEntry
    clock: ClockSync
    gate: CommandGate
    last_heard_ns: int = 0
    sessions: set[int] = field(default_factory=set)


class ControlLease:
    """Holder, waiting requester and every known key's gate."""

    def __init__(
        self, operators: dict[bytes, OperatorEntry], max_age_ns: int, request_timeout_ns: int
    ) -> None:
        self.operators = operators
        self.max_age_ns = max_age_ns
        self.request_timeout_ns = request_timeout_ns
        self.peers: dict[bytes, Peer] = {}
        self.holder: bytes | None = None
        self.pending: bytes | None = None
        self.pending_until_ns = 0
        #: the gate nobody feeds: the deadman's reference while nobody holds the lease
        self.idle_gate = CommandGate(ClockSync(), max_age_ns)
        self.changes = 0

    def peer(self, key: bytes) -> Peer | None:
        """The key's state, made on first contact; None for a key not in the roster."""
        peer = self.peers.get(key)
        if peer is None:
            entry = self.operators.get(key)
            if entry is None:
                return None
            clock = ClockSync()
            peer = self.peers[key] = Peer(entry, clock, CommandGate(clock, self.max_age_ns))
        return peer

    @property
    def holder_gate(self) -> CommandGate:
        """The gate whose newest fresh message the deadman counts from."""
        if self.holder is None:
            return self.idle_gate
        return self.peers[self.holder].gate

    def holder_name(self) -> str | None:
        return None if self.holder is None else self.operators[self.holder].name

    def _set_holder(self, key: bytes | None) -> None:
        if key != self.holder:
            log.info(
                "control lease: %s -> %s",
                self.holder_name() or "nobody",
                "nobody" if key is None else self.operators[key].name,
            )
            self.holder = key
            self.changes += 1
        if key is not None and key == self.pending:
            self.pending = None

    def handle(self, key: bytes, cmd: Command, now_ns: int) -> str:
        """Act on one admitted lease action from ``key``; the outcome's counter name."""
        self.tick(now_ns)
        role = self.operators[key].role
        if cmd.action == "lease_request":
            if role != "controller":
                return REFUSED_ROLE
            if self.holder == key:
                return HELD
            if self.holder is None:
                self._set_holder(key)
                return GRANTED
            self.pending = key
            self.pending_until_ns = now_ns + self.request_timeout_ns
            return PENDING
        if cmd.action == "lease_grant":
            if self.holder != key:
                return REFUSED_NOT_HOLDER
            grantee = cmd.grantee if cmd.grantee is not None else self.pending
            entry = None if grantee is None else self.operators.get(grantee)
            if entry is None or entry.role != "controller":
                return REFUSED_GRANTEE
            if not self._fresh(grantee, now_ns):
                # handing the arm to a key we have not heard lately would trip the deadman at
                # once and leave nobody in control: the holder keeps it
                return REFUSED_SILENT
            self._set_holder(grantee)
            return HANDED_OVER
        # lease_release
        if self.pending == key:
            self.pending = None
        if self.holder != key:
            return REFUSED_NOT_HOLDER
        if self.pending is not None and self._fresh(self.pending, now_ns):
            self._set_holder(self.pending)
            return HANDED_OVER
        self._set_holder(None)
        return RELEASED

    def _fresh(self, key: bytes, now_ns: int) -> bool:
        """Has ``key`` sent something fresh lately (its gate's newest fresh message)?"""
        last = self.peer(key).gate.last_fresh_ns
        return last is not None and now_ns - last <= self.max_age_ns

    def replace_roster(self, operators: dict[bytes, OperatorEntry]) -> list[str]:
        """Take a re-read roster; what changed, in words (for the log).

        A key no longer in it is forgotten (its clock, gate and sessions); a key
        whose role changed keeps its clock. A holder that is gone, or no longer a
        controller, loses the lease at once, and so does a waiting request.
        """
        changed = []
        for key in list(self.peers):
            entry = operators.get(key)
            old = self.peers[key].entry
            if entry is None:
                del self.peers[key]
            elif entry != old:
                self.peers[key].entry = entry
        for key, old in self.operators.items():
            entry = operators.get(key)
            if entry is None:
                changed.append(f"{old.name} removed")
            elif entry.role != old.role or entry.name != old.name:
                changed.append(f"{old.name} ({old.role}) now {entry.name} ({entry.role})")
        changed += [
            f"{e.name} ({e.role}) added" for k, e in operators.items() if k not in self.operators
        ]
        self.operators = operators

        def may_hold(key: bytes | None) -> bool:
            return key is not None and key in operators and operators[key].role == "controller"

        if self.pending is not None and not may_hold(self.pending):
            self.pending = None
        if self.holder is not None and not may_hold(self.holder):
            self.holder = None  # not _set_holder: the old name may be gone from the roster
            self.changes += 1
            changed.append("the lease holder may no longer hold it: nobody holds it now")
        return changed

    def tick(self, now_ns: int) -> str | None:
        """Let a request nobody granted lapse."""
        if self.pending is not None and now_ns >= self.pending_until_ns:
            self.pending = None
            return TIMED_OUT
        return None

    def expire(self, now_ns: int) -> None:
        """The holder went silent (the deadman tripped): a fresh waiting requester takes over."""
        self.tick(now_ns)
        nxt = self.pending
        if nxt is not None and not self._fresh(nxt, now_ns):
            nxt = None
        self._set_holder(nxt)
