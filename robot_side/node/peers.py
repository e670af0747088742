"""Who may command the robot: a roster of signing keys with a control lease, or one peer.

The command desk asks the same four questions of either: whose message is
this (``find``), does its sender hold control (``holds``), what a lease
action does (``lease_action``), and whose silence the deadman counts
(``holder_gate``). Without a roster the link is unsigned and has exactly
one operator, who always holds control: the same admission then serves both.
"""

from __future__ import annotations

from common.clocks.clock_sync import ClockSync
from common.keys.roster import OperatorEntry
from common.wire.messages import Command, Message
from robot_side.node.commands.command_gate import CommandGate
from robot_side.node.commands.lease import ControlLease, Peer

#: the one operator of an unsigned link (a stop latched by it says "operator")
ONE_OPERATOR = OperatorEntry(name="operator", role="controller", curve_key=None, signing_key=None)
#: counted for a lease action on an unsigned link: its one operator always holds control
LEASE_WITHOUT_ROSTER = "lease_actions_without_roster"
#: refusals of a message before its sender is known, each the counter it increments
UNSIGNED = "messages_unsigned"
UNKNOWN_SIGNER = "messages_unknown_signer"


class OnePeer:
    """The unsigned link as a roster of one: every message is the one operator's."""

    lease: ControlLease | None = None

    def __init__(self, clock: ClockSync, max_age_ns: int) -> None:
        self.peer = Peer(ONE_OPERATOR, clock, CommandGate(clock, max_age_ns))

    def find(self, msg: Message) -> tuple[bytes | None, Peer] | str:
        return None, self.peer

    def holds(self, key: bytes | None) -> bool:
        return True

    def lease_action(self, key: bytes | None, cmd: Command, now_ns: int) -> str:
        return LEASE_WITHOUT_ROSTER

    @property
    def holder_gate(self) -> CommandGate:
        return self.peer.gate

    def last_heard_ns(self, key: bytes | None) -> int:
        return self.peer.last_heard_ns

    def entry(self, key: bytes | None) -> OperatorEntry | None:
        """The one operator, whoever signed (a controller)."""
        return ONE_OPERATOR


class RosterPeers:
    """Signed messages from the roster's keys; only the lease holder commands (lease.py)."""

    def __init__(self, lease: ControlLease) -> None:
        self.lease = lease

    def find(self, msg: Message) -> tuple[bytes | None, Peer] | str:
        """(signer, its state), or the refusal's counter.

        The codec has already checked every signature (a message whose ``sig``
        does not verify never gets here); what is left is whether its signer
        is one of ours.
        """
        key = getattr(msg, "signer", None)
        if key is None:
            return UNSIGNED
        peer = self.lease.peer(key)
        if peer is None:
            return UNKNOWN_SIGNER
        return key, peer

    def holds(self, key: bytes | None) -> bool:
        return key == self.lease.holder

    def lease_action(self, key: bytes | None, cmd: Command, now_ns: int) -> str:
        return self.lease.handle(key, cmd, now_ns)

    @property
    def holder_gate(self) -> CommandGate:
        return self.lease.holder_gate

    def last_heard_ns(self, key: bytes | None) -> int:
        peer = None if key is None else self.lease.peer(key)
        return peer.last_heard_ns if peer is not None else 0

    def entry(self, key: bytes | None) -> OperatorEntry | None:
        """``key``'s roster entry in force now; None for no key or a stranger.

        Read on the video thread too: one lookup in the roster in force, never a change.
        """
        return None if key is None else self.lease.operators.get(key)
