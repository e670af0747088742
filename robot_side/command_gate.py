"""Which operator messages the robot acts on: fresh by the operator's clock, in order, once.

A command is a wish the operator had when it was sent. Acting on it later
than that is acting on a wish the operator may no longer have, so every
timing decision here is taken from the operator's send time mapped onto the
robot's clock (the heartbeat offset, ``common.clock_sync``), not from when
the robot got round to reading it:

- **fresh**: a command older than ``max_age_ns`` is refused. A backlog (a
  burst, a congested link, a stalled reader) therefore ages out instead of
  moving the arm seconds after the operator let go.
- **the deadman counts from the operator**: the newest fresh message's send
  time, never later than its arrival, starts the deadman. Queued old
  messages cannot extend it; a timestamp from the future cannot either.
- **once, in order**: within one operator session (the ``session`` field,
  random per operator run), ``seq`` and ``t_send_ns`` must both increase. A
  replayed or reordered command is refused (``common.replay_window``, the
  window signed telemetry uses too, here with no room for reordering). CURVE
  already stops a stranger on the network from replaying anything; this
  stops a replay by anyone who can reach the socket (a key holder, or anyone
  on a plain loopback link).
- **before the clock offset is known** (the first heartbeat round trip,
  about 100 ms after an operator connects) no send time can be judged, so
  only commands that cannot start motion are acted on.

``arm_stop``, ``arm_jog_end`` and ``gripper_hold`` only ever end motion:
they are acted on however old they are (still once, in order), since
refusing a late stop could only keep the arm moving longer. ``arm_resume``
is the opposite (it lets the arm move again): it must be fresh like a jog.
"""

from __future__ import annotations

from common.clock_sync import ClockSync
from common.messages import Command
from common.replay_window import ReplayWindow

#: Commands that can only end motion: safe to act on when late or before the clock is known.
SAFE_WHEN_LATE = frozenset({"arm_stop", "arm_jog_end", "gripper_hold"})

#: Refusal reasons, each the name of the counter it increments.
UNSYNCED = "commands_unsynced"
FROM_FUTURE = "commands_from_future"
REPLAYED = "commands_replayed"
STALE = "commands_stale"


class CommandGate:
    """Admission of operator commands and the deadman's clock, on the operator's time."""

    MAX_SESSIONS = 16  # operator runs remembered; the oldest is forgotten first

    def __init__(self, clock: ClockSync, max_age_ns: int) -> None:
        if max_age_ns <= 0:
            raise ValueError(f"max_age_ns must be positive, not {max_age_ns}")
        self.clock = clock
        self.max_age_ns = max_age_ns
        #: per operator session: seq and send time must both increase (no reordering)
        self.window = ReplayWindow(width=0, max_sessions=self.MAX_SESSIONS)
        #: send time (our clock) of the newest fresh message from the operator, or None
        self.last_fresh_ns: int | None = None

    def sent_at(self, t_send_ns: int, t_recv_ns: int) -> int | None:
        """The operator's send time on our clock, never after arrival; None before the offset."""
        offset = self.clock.offset_ns
        if offset is None:
            return None
        return min(t_send_ns - offset, t_recv_ns)

    def heard(self, t_send_ns: int, t_recv_ns: int, now_ns: int) -> bool:
        """Any message from the operator: does it keep the deadman alive? (True if fresh.)

        Before the clock offset is known, arrival time stands in for the send
        time: nothing that moves the arm is accepted then anyway.
        """
        sent = self.sent_at(t_send_ns, t_recv_ns)
        if sent is None:
            sent = t_recv_ns
        if now_ns - sent > self.max_age_ns:
            return False
        if self.last_fresh_ns is None or sent > self.last_fresh_ns:
            self.last_fresh_ns = sent
        return True

    def admit(self, cmd: Command, t_recv_ns: int, now_ns: int) -> tuple[str | None, int | None]:
        """(refusal reason or None, the command's send time on our clock or None)."""
        offset = self.clock.offset_ns
        if offset is None:
            return (None if cmd.action in SAFE_WHEN_LATE else UNSYNCED), None
        mapped = cmd.t_send_ns - offset
        if mapped - t_recv_ns > self.max_age_ns:  # clock error is far smaller than this
            return FROM_FUTURE, None
        session = cmd.session or 0
        if self.window.replayed(session, Command.TOPIC, cmd.seq, cmd.t_send_ns):
            return REPLAYED, None
        sent = min(mapped, t_recv_ns)
        if now_ns - sent > self.max_age_ns and cmd.action not in SAFE_WHEN_LATE:
            return STALE, sent
        self.window.accept(session, Command.TOPIC, cmd.seq, cmd.t_send_ns)
        self.heard(cmd.t_send_ns, t_recv_ns, now_ns)
        return None, sent
