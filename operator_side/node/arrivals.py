"""What arrives from the robot: believed or dropped, then the clock, the link and the views.

Each message the subscriber hands over passes, in order:

1. the robot's key: with ``link.robot_key_file`` a message not signed by it
   is dropped (a router, or anyone on the path, cannot make the palm move);
2. the telemetry gate (telemetry_gate.py): a signed message is believed
   once, fresh, and from the robot run that answered our heartbeat;
3. then a stimulus feeds the link statistics and becomes the one the palm
   renders (unless it is older than the newest); a heartbeat syncs the clock,
   states the lease and confirms a gripper command; a frame and a video
   signal go to the live views.

``RobotHeard`` keeps when the robot was last heard and its run (session),
which every message we send echoes.
"""

from __future__ import annotations

import logging
import threading
from collections import Counter
from collections.abc import Callable
from typing import Any

import numpy as np

from common.clocks.clock_sync import ClockSync
from common.logs import BurstLog
from common.tactile.contract import matches_pattern
from common.wire.link_stats import LinkStats
from common.wire.messages import Heartbeat, Stimulus, TactileFrame, VideoSignal
from common.wire.transport import Receiver
from operator_side.node.lease_view import LeaseView
from operator_side.node.operator_channels import OperatorChannels
from operator_side.node.telemetry_gate import REFUSALS as TELEMETRY_REFUSALS
from operator_side.node.telemetry_gate import UNPROVEN, TelemetryGate

log = logging.getLogger(__name__)

RESTART_SEQ_GAP = 1000  # a sequence number this far back means the robot restarted


class RobotHeard:
    """When the robot was last heard (its send time, on our clock) and which run it is."""

    def __init__(self, clock: ClockSync, blind_after_ms: float) -> None:
        self.clock = clock
        self.blind_after_ms = blind_after_ms
        #: the send time of the robot's newest stimulus or heartbeat, on our clock
        self.heard_ns: int | None = None
        #: the robot run (its session) we last heard, echoed on everything we send: it proves
        #: to a robot that restarted that our messages are of its run, not recorded before
        self.session: int | None = None

    def heard(self, t_send_ns: int, t_recv: int) -> None:
        """The robot was alive at ``t_send_ns``: a backlog delivered late does not count as now."""
        local = self.to_local(t_send_ns, t_recv)
        if self.heard_ns is None or local > self.heard_ns:
            self.heard_ns = local

    def sees_robot(self, now: int) -> bool:
        """Whether the robot's telemetry is fresh enough to steer by (``jog_blind_after_ms``)."""
        heard = self.heard_ns
        return heard is not None and (now - heard) / 1e6 <= self.blind_after_ms

    def to_local(self, t_remote_ns: int, t_recv_ns: int) -> int:
        """A robot timestamp on our clock; before the offset is known, the receive time."""
        if not self.clock.is_synced:
            return t_recv_ns
        return min(self.clock.to_local(t_remote_ns), t_recv_ns)


class Arrivals:
    """The robot's messages as the node believes them: the stimulus, frame and robot stats."""

    def __init__(
        self,
        clock: ClockSync,
        heard: RobotHeard,
        lease: LeaseView,
        *,
        robot_key: bytes | None,
        gate: TelemetryGate | None,
        counters: Counter[str],
        recording: OperatorChannels,
        on_robot_stats: Callable[[dict[str, float]], None],
    ) -> None:
        """``on_robot_stats``: each robot heartbeat's stats (the outbox confirms a gripper
        command with them)."""
        self.clock = clock
        self.heard = heard
        self.lease = lease
        self.robot_key = robot_key
        self.gate = gate
        self.counters = counters
        self.recording = recording
        self.on_robot_stats = on_robot_stats
        #: loss, latency, jitter and staleness of the stimulus stream
        self.link_stats = LinkStats(clock=clock)
        #: called on the node's thread with each video signal the robot sends (the dashboard)
        self.video_signal_handler: Callable[[VideoSignal], None] | None = None
        #: guards what the live views read from another thread
        self.lock = threading.Lock()
        self.stimulus: Stimulus | None = None
        #: (session, seq) of the change the stimulus's cells came with (``_content_of``)
        self.content: tuple[int | None, int] | None = None
        self.local_capture_ns: int | None = None  # newest confirmation, local clock
        self.latency_capture_ns: int | None = None  # a stimulus's capture, until rendered
        self.frame: TactileFrame | None = None
        self.robot_stats: dict[str, float] = {}
        self._forged_log = BurstLog(log, "telemetry dropped: not signed by the robot's key")
        #: one per reason, so a replay's first example is not hidden behind another reason's
        self._refusal_logs = {
            reason: BurstLog(log, "signed telemetry refused (replay window)")
            for reason in TELEMETRY_REFUSALS
        }

    def receive(self, sub: Receiver, relinking: bool) -> tuple[bool, int]:
        """Drain the socket: (a new stimulus arrived, when the newest believed one arrived).

        ``relinking``: the palm is not rendering (stale or down), so a heartbeat
        that may confirm the stimulus again counts as new.
        """
        new, last_rx = False, 0
        robot_key, gate = self.robot_key, self.gate
        # recording: each message's bytes as they crossed the link, to record them as they were
        wires: list[bytes] | None = [] if self.recording.on else None
        batch = sub.drain() if wires is None else sub.drain(wires=wires)
        for i, (msg, t_recv) in enumerate(batch):
            if robot_key is not None and msg.signer != robot_key:
                # not from our robot: a router (or anyone on the path) cannot make the palm move
                what = "telemetry_unsigned" if msg.signer is None else "telemetry_forged"
                self.counters[what] += 1
                self._forged_log(f"{type(msg).__name__}: {what}")
                continue
            if gate is not None and not self._admitted(gate, msg, t_recv):
                continue  # ours, but not now: a replay, an old run, or too old to act on
            last_rx = t_recv
            if isinstance(msg, Stimulus):
                new |= self._on_stimulus(msg, t_recv, None if wires is None else wires[i])
            elif isinstance(msg, Heartbeat):
                self._on_heartbeat(msg, t_recv)
                new |= relinking  # it may confirm a stimulus again
            elif isinstance(msg, TactileFrame):
                with self.lock:
                    self.frame = msg
            elif isinstance(msg, VideoSignal) and self.video_signal_handler is not None:
                self.video_signal_handler(msg)
            else:
                self.counters["messages_unexpected"] += 1
        return new, last_rx

    def _admitted(self, gate: TelemetryGate, msg: Any, t_recv: int) -> bool:
        """Whether the telemetry gate lets the robot's signed message through; counted if not."""
        believed = gate.session
        refusal = gate.admit(msg, t_recv)
        if refusal is None:
            if gate.session != believed:
                self.counters["telemetry_sessions"] += 1
                retired = "" if believed is None else f", its run {believed:016x} retired"
                log.info(
                    "robot run %016x believed: a heartbeat answered ours%s (%d refused so far "
                    "as unproven)",
                    gate.session,
                    retired,
                    self.counters[UNPROVEN],
                )
            return True
        self.counters[refusal] += 1
        if refusal == UNPROVEN:
            if isinstance(msg, Heartbeat) and msg.session is not None:
                # Echo the run we hear (signed by our robot) before we believe it: the robot
                # acts on our heartbeats only once they echo its run, and only then answers
                # them, which is what proves the run to us. Nothing else is taken from it.
                self.heard.session = msg.session
            return False  # they come at every start, until the robot answers us
        session = getattr(msg, "session", None)
        if session is None:
            self._refusal_logs[refusal](
                f"{type(msg).__name__} seq {msg.seq} signed without a session: the robot node "
                "predates the replay window (docs/protocol.md); update it"
            )
            return False
        offset = self.clock.offset_ns
        age = (
            "" if offset is None else f", sent {(t_recv + offset - msg.t_send_ns) / 1e6:.0f} ms ago"
        )
        self._refusal_logs[refusal](
            f"{type(msg).__name__} {refusal}: run {session:016x}, seq {msg.seq}{age}"
        )
        return False

    def _on_stimulus(self, msg: Stimulus, t_recv: int, wire: bytes | None) -> bool:
        self.link_stats.on_message(msg.seq, msg.t_send_ns, t_recv)
        self.heard.heard(msg.t_send_ns, t_recv)
        last = self.stimulus
        if (
            last is not None
            and last.session == msg.session  # a new run numbers from 1 again
            and last.seq - RESTART_SEQ_GAP < msg.seq <= last.seq
        ):
            self.counters["stimuli_out_of_order"] += 1
            return False
        self.counters["stimuli_received"] += 1
        if wire is not None:
            self.recording.stimulus(msg.seq, t_recv, wire)
        local_capture = self.heard.to_local(msg.t_capture_ns, t_recv)
        self.content = _content_of(msg, last, self.content)
        with self.lock:
            self.stimulus = msg
            self.local_capture_ns = local_capture
        self.latency_capture_ns = local_capture
        if msg.sim_truth_pattern is not None and msg.contact:
            self.counters["stimuli_with_truth"] += 1
            if matches_pattern(msg.stimulus, msg.sim_truth_pattern):
                self.counters["stimuli_matching_truth"] += 1
        return True

    def _on_heartbeat(self, msg: Heartbeat, t_recv: int) -> None:
        if msg.node != "robot":
            return
        self.counters["heartbeats_received"] += 1
        echo_send, echo_recv = msg.echo_t_send_ns, msg.echo_t_recv_ns
        if msg.echo_signer is not None and msg.echo_signer != self.lease.own_key:
            echo_send = echo_recv = None  # it answers another operator's heartbeat
        self.clock.on_heartbeat(msg.t_send_ns, echo_send, echo_recv, t_recv)
        self.heard.heard(msg.t_send_ns, t_recv)
        if msg.session is not None:
            self.heard.session = msg.session
        self.lease.on_heartbeat(msg)
        # merged: across the fabric most heartbeats carry only what an operator acts on (the
        # stop latch, the gripper's ack) and the whole counters once a second
        self.robot_stats = {**self.robot_stats, **msg.stats}
        self.on_robot_stats(msg.stats)
        stim, named = self.stimulus, msg.stimulus_seq
        if (
            stim is not None
            and named is not None
            and msg.t_capture_ns is not None
            and (named == stim.seq or (msg.session, named) == self.content)
        ):
            local = self.heard.to_local(msg.t_capture_ns, t_recv)
            with self.lock:
                if self.local_capture_ns is None or local > self.local_capture_ns:
                    self.local_capture_ns = local

    def take_latency_capture(self) -> int | None:
        """The capture time of a stimulus not yet rendered (once: the palm's latency sample)."""
        captured, self.latency_capture_ns = self.latency_capture_ns, None
        return captured

    def views(self) -> tuple[Stimulus | None, TactileFrame | None, dict[str, float]]:
        """(stimulus, frame, robot stats) for a live view, from any thread."""
        with self.lock:
            return self.stimulus, self.frame, dict(self.robot_stats)


def _content_of(
    msg: Stimulus, last: Stimulus | None, content: tuple[int | None, int] | None
) -> tuple[int | None, int] | None:
    """The change whose cells ``msg`` renders, as the robot's heartbeats name it.

    A robot's heartbeat names its last change (``stimulus_seq``), not the
    keyframes that repeat it, so that one of them lost does not leave the
    palm unconfirmed while the heartbeats say nothing changed. A keyframe
    keeps the change we have when it repeats its cells; with other cells it
    repeats a change we lost, which we cannot name: until the next change,
    only the keyframes confirm (as before).
    """
    if not msg.keyframe:
        return msg.session, msg.seq
    same = (
        last is not None
        and last.session == msg.session
        and last.pattern == msg.pattern
        and np.array_equal(last.stimulus, msg.stimulus)
    )
    return content if same else None
