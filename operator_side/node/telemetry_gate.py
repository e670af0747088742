"""Which signed robot telemetry the operator believes: this robot run's, fresh, once.

A signature proves who made a message, not when: a stimulus captured off
the wire (by a router, or anyone on the path) verifies as well a second later
as it did the first time. So the robot stamps a random ``session`` per node
run (its boot id) on everything it signs, beside the per-stream ``seq`` and
its send time, and the operator refuses, counting each under its name:

- ``telemetry_without_session``: signed, but no session: a robot node built
  before the replay window (update it; nothing else would stop a replay).
- ``telemetry_old_session``: from a run the robot has since restarted out of.
- ``telemetry_unproven_session``: from a run not yet shown to be alive now. A
  run is believed once one of its heartbeats answers one of our own recent
  heartbeats (its ``echo_t_send_ns`` is one we sent, within ``proof_ns``): a
  recording cannot answer a heartbeat sent after it was made. Until then
  nothing of it is acted on; a few of these at every start and every robot
  restart are the messages that came before that answer.
- ``telemetry_from_future`` / ``telemetry_stale``: its send time, on our clock
  (the heartbeat offset), is more than ``max_age_ns`` after its arrival or
  before it.
- ``telemetry_replayed``: a ``seq`` of its stream already accepted, or too far
  behind the newest (``common.wire.replay_window``, the commands' window, here with
  room for ``WIDTH`` messages of reordering per stream).

A new run retires the one before (a restarted node: its old messages are
refused from then on) and resets the clock estimate, since a restarted robot
may count on another clock. The robot's command gate is the mirror image
(``robot_side/node/commands/command_gate.py``).
"""

from __future__ import annotations

import collections

from common.clocks.clock_sync import ClockSync
from common.wire.messages import Heartbeat, Message
from common.wire.replay_window import ReplayWindow

#: Refusal reasons, each the name of the counter it increments.
WITHOUT_SESSION = "telemetry_without_session"
OLD_SESSION = "telemetry_old_session"
UNPROVEN = "telemetry_unproven_session"
FROM_FUTURE = "telemetry_from_future"
REPLAYED = "telemetry_replayed"
STALE = "telemetry_stale"
REFUSALS = (WITHOUT_SESSION, OLD_SESSION, UNPROVEN, FROM_FUTURE, REPLAYED, STALE)


class TelemetryGate:
    """Admission of one robot's signed telemetry, on the robot's time and run."""

    WIDTH = 64  # messages of reordering tolerated per stream (about 1 s of stimuli at 60 Hz)
    MAX_RETIRED = 16  # earlier runs remembered; an older one is still refused as stale

    def __init__(self, clock: ClockSync, max_age_ns: int, own_key: bytes | None = None) -> None:
        if max_age_ns <= 0:
            raise ValueError(f"max_age_ns must be positive, not {max_age_ns}")
        self.clock = clock
        self.max_age_ns = max_age_ns
        #: how recent a heartbeat of ours a new run's answer must name to be believed
        self.proof_ns = max(2_000_000_000, 2 * max_age_ns)
        self.own_key = own_key
        self.session: int | None = None  # the run we believe
        self.sessions_seen = 0
        self.window = ReplayWindow(width=self.WIDTH, max_sessions=1)
        self._retired: collections.OrderedDict[int, None] = collections.OrderedDict()
        self._sent: collections.deque[int] = collections.deque(maxlen=256)

    def heartbeat_sent(self, t_send_ns: int) -> None:
        """One of our heartbeats left: a new robot run proves itself by answering it."""
        self._sent.append(t_send_ns)

    def admit(self, msg: Message, t_recv_ns: int) -> str | None:
        """The refusal reason, or None when the message may be acted on (then recorded)."""
        session = getattr(msg, "session", None)
        if session is None:
            return WITHOUT_SESSION
        if session != self.session:
            if session in self._retired:
                return OLD_SESSION
            if not self._answers_us(msg, t_recv_ns):
                return UNPROVEN
            self._believe(session)
        offset = self.clock.offset_ns
        mapped = None if offset is None else msg.t_send_ns - offset
        if mapped is not None and mapped - t_recv_ns > self.max_age_ns:
            return FROM_FUTURE
        if self.window.replayed(session, msg.TOPIC, msg.seq, msg.t_send_ns):
            return REPLAYED
        if mapped is not None and t_recv_ns - min(mapped, t_recv_ns) > self.max_age_ns:
            return STALE
        self.window.accept(session, msg.TOPIC, msg.seq, msg.t_send_ns)
        return None

    def _answers_us(self, msg: Message, t_recv_ns: int) -> bool:
        if not isinstance(msg, Heartbeat) or msg.node != "robot":
            return False
        if msg.echo_signer is not None and msg.echo_signer != self.own_key:
            return False  # it answers another operator's heartbeat
        t1 = msg.echo_t_send_ns
        return t1 is not None and 0 <= t_recv_ns - t1 <= self.proof_ns and t1 in self._sent

    def _believe(self, session: int) -> None:
        if self.session is not None:
            self._retired[self.session] = None
            while len(self._retired) > self.MAX_RETIRED:
                self._retired.popitem(last=False)
        self.session = session
        self.sessions_seen += 1
        self.window.clear()
        self.clock.reset()  # the new run's heartbeats give the offset again, from this one on
