"""Which operator messages the robot acts on: fresh by the operator's clock, in order, once.

A command is a wish the operator had when it was sent. Acting on it later
than that is acting on a wish the operator may no longer have, so every
timing decision here is taken from the operator's send time mapped onto the
robot's clock (the heartbeat offset, ``common.clocks.clock_sync``), not from when
the robot got round to reading it:

- **fresh**: a command older than ``max_age_ns`` is refused. A backlog (a
  burst, a congested link, a stalled reader) therefore ages out instead of
  moving the arm seconds after the operator let go.
- **the deadman counts from the operator**: the newest fresh message's send
  time, never later than its arrival, starts the deadman. Queued old
  messages cannot extend it; a timestamp from the future cannot either.
- **once, in order**: within one operator boot (the ``session`` field,
  random per operator run), each stream's ``seq`` must increase: commands,
  heartbeats and video signals alike (``common.wire.replay_window``, the window
  signed telemetry uses too, here with no room for reordering). CURVE
  already stops a stranger on the network from replaying anything; this
  stops a replay by anyone who can reach the socket (a key holder, or anyone
  on a plain loopback link).
- **of this robot run**: a robot that restarted remembers no window, so the
  first message of each stream of a boot must prove it was sent to this run:
  its ``echo_session`` is the robot's own ``session`` (random per robot run),
  which nothing recorded before the run can carry. Without that proof a
  message is refused (``messages_unproven``), with one exception below.
- **before the clock offset is known** (the first heartbeat round trip,
  about 100 ms after an operator connects) no send time can be judged, so
  only commands that cannot start motion are acted on.

``arm_stop``, ``arm_jog_end`` and ``gripper_hold`` only ever end motion:
they are acted on however old they are (still once, in order), since
refusing a late stop could only keep the arm moving longer. ``arm_resume``
is the opposite (it lets the arm move again): it must be fresh like a jog.

An ``arm_stop`` without the proof (its sender had not yet heard this robot
run, or its fields are malformed) is ``PENDING``, never simply refused: the
command desk stops the arm at once and latches the stop only if, within
``STOP_PROOF_NS``, the sender's boot proves it is live and its clock places
the stop after this run started (``judge_pending``). A replayed old stop
therefore stops the arm for a moment and latches nothing; a genuine one from
an operator that is a heartbeat behind is not lost. That is the trade-off:
a genuine stop refused would keep an arm moving; a replayed one costs a jog
at most ``STOP_PROOF_NS`` of stillness.
"""

from __future__ import annotations

from dataclasses import dataclass

from common.clocks.clock_sync import ClockSync
from common.wire.messages import Command, Heartbeat, Message
from common.wire.replay_window import ReplayWindow

#: Commands that can only end motion: safe to act on when late or before the clock is known.
SAFE_WHEN_LATE = frozenset({"arm_stop", "arm_jog_end", "gripper_hold"})

#: Refusal reasons, each the name of the counter it increments.
UNSYNCED = "commands_unsynced"
FROM_FUTURE = "commands_from_future"
REPLAYED = "commands_replayed"
STALE = "commands_stale"
WITHOUT_SESSION = "messages_without_session"
UNPROVEN = "messages_unproven"
#: a replay of each kind, counted under its own name
REPLAYED_BY_TOPIC = {
    Command.TOPIC: REPLAYED,
    Heartbeat.TOPIC: "heartbeats_replayed",
    b"VSIG": "video_signals_replayed",
}
#: not a refusal: an arm_stop whose proof is still to come (the desk stops the arm now)
PENDING = "arm_stops_pending"
#: how long a pending stop waits for its sender's proof before it is refused
STOP_PROOF_NS = 2_000_000_000
#: what a pending stop comes to, each the counter it increments
STOP_PROVEN = "arm_stops_proven"
STOP_BEFORE_RUN = "arm_stops_before_this_run"
STOP_UNPROVEN = "arm_stops_unproven"
#: the fields a stop needs to be placed in the replay window
_PLACES_STOP = frozenset({"seq", "session", "echo_session"})


def defective(cmd: Command) -> set[str]:
    """The names of a stop's fields the codec could not read (``Command.defects``)."""
    return {d.partition(":")[0] for d in cmd.defects}


@dataclass(frozen=True, slots=True)
class RobotRun:
    """This robot node's run: its boot id (``session``) and when it started (our clock)."""

    session: int
    start_ns: int


class CommandGate:
    """Admission of one operator key's messages and the deadman's clock, on its time."""

    MAX_SESSIONS = 16  # operator runs remembered; the oldest is forgotten first
    MAX_RETIRED = 1024  # runs forgotten, still refused

    def __init__(self, clock: ClockSync, max_age_ns: int) -> None:
        if max_age_ns <= 0:
            raise ValueError(f"max_age_ns must be positive, not {max_age_ns}")
        self.clock = clock
        self.max_age_ns = max_age_ns
        #: per operator boot and stream: seq must increase (no reordering)
        self.window = ReplayWindow(
            width=0, max_sessions=self.MAX_SESSIONS, by_time=False, retired=self.MAX_RETIRED
        )
        #: send time (our clock) of the newest fresh message from the operator, or None
        self.last_fresh_ns: int | None = None

    def once(self, msg: Message, run: RobotRun) -> str | None:
        """The replay window's word on any operator message: a refusal, or None (unrecorded)."""
        session = msg.session
        if session is None:
            return WITHOUT_SESSION
        if self.window.replayed(session, msg.TOPIC, msg.seq, msg.t_send_ns):
            return REPLAYED_BY_TOPIC.get(msg.TOPIC, REPLAYED)
        if not self.window.has(session, msg.TOPIC) and msg.echo_session != run.session:
            return UNPROVEN
        return None

    def admit_signal(self, msg: Message, run: RobotRun) -> str | None:
        """A heartbeat or video signal: refused, or accepted (recorded) with None."""
        refusal = self.once(msg, run)
        if refusal is None:
            self.window.accept(msg.session, msg.TOPIC, msg.seq, msg.t_send_ns)
        return refusal

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

    def admit(
        self, cmd: Command, t_recv_ns: int, now_ns: int, run: RobotRun
    ) -> tuple[str | None, int | None]:
        """(refusal reason, ``PENDING`` or None; the command's send time on our clock or None)."""
        stop = cmd.action == "arm_stop"
        if stop and not _PLACES_STOP.isdisjoint(defective(cmd)):
            return PENDING, None  # the window cannot place it: only its sender's proof can
        refusal = self.once(cmd, run)
        if refusal is not None:
            return (PENDING if stop and refusal != REPLAYED else refusal), None
        stamp_ok = "t_send_ns" not in defective(cmd)  # a stop's may be unreadable (then 0)
        offset = self.clock.offset_ns
        if offset is None or not stamp_ok:
            if cmd.action not in SAFE_WHEN_LATE:
                return UNSYNCED, None
            self.window.accept(cmd.session, Command.TOPIC, cmd.seq, cmd.t_send_ns)
            return None, None
        mapped = cmd.t_send_ns - offset
        if mapped - t_recv_ns > self.max_age_ns:  # clock error is far smaller than this
            if cmd.action not in SAFE_WHEN_LATE:
                return FROM_FUTURE, None
            self.window.accept(cmd.session, Command.TOPIC, cmd.seq, cmd.t_send_ns)
            return None, None  # a stop is a stop whatever its stamp; it feeds no deadman
        sent = min(mapped, t_recv_ns)
        if now_ns - sent > self.max_age_ns and cmd.action not in SAFE_WHEN_LATE:
            return STALE, sent
        self.window.accept(cmd.session, Command.TOPIC, cmd.seq, cmd.t_send_ns)
        self.heard(cmd.t_send_ns, t_recv_ns, now_ns)
        return None, sent

    def judge_pending(self, cmd: Command, t_recv_ns: int, now_ns: int, run: RobotRun) -> str | None:
        """What a pending stop comes to: ``STOP_PROVEN``, a refusal, or None (still waiting).

        Proven: its boot has since shown it hears this run (its window is set),
        and, once the clock offset is known, the stop was sent after this run
        started (a stop recorded before a robot restart, from a boot still
        running, is not). A stop whose send time is unreadable has only its
        boot's proof. Past ``STOP_PROOF_NS`` without proof it is refused.
        """
        session = cmd.session
        live = session is not None and any(
            self.window.has(session, topic) for topic in REPLAYED_BY_TOPIC
        )
        if live:
            if "t_send_ns" in defective(cmd):
                return STOP_PROVEN
            est = self.clock.estimate(now_ns)
            if est is not None:
                mapped = cmd.t_send_ns - est.offset_ns
                return (
                    STOP_PROVEN if mapped >= run.start_ns - est.uncertainty_ns else STOP_BEFORE_RUN
                )
        if now_ns - t_recv_ns > STOP_PROOF_NS:
            return STOP_UNPROVEN
        return None
