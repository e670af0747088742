"""The operator's heartbeat: it keeps the robot's deadman alive and samples the clock offset.

It echoes the robot's newest heartbeat (the robot measures the offset and
the round trip from it), carries this run's session and echoes the robot's
(proof to a restarted robot that we hear its run), and tells the telemetry
gate when it left (a robot's answer proves its run only if sent after it).
Each one sent is recorded with the link's state and the node's stats.
"""

from __future__ import annotations

from collections.abc import Callable

from common.clocks.clock_sync import ClockSync
from common.wire.messages import Heartbeat
from common.wire.transport import Sender
from operator_side.node.arrivals import RobotHeard
from operator_side.node.operator_channels import OperatorChannels
from operator_side.node.telemetry_gate import TelemetryGate


class HeartbeatOut:
    """Builds, sends and records the operator's heartbeats."""

    def __init__(
        self,
        clock: ClockSync,
        heard: RobotHeard,
        gate: TelemetryGate | None,
        pub: Callable[[], Sender],
        *,
        session: int,
        now: Callable[[], int],
        recording: OperatorChannels,
    ) -> None:
        self.clock = clock
        self.heard = heard
        self.gate = gate
        self.pub = pub
        self.session = session
        self.now = now
        self.recording = recording
        self.seq = 0

    def send(self, link_state: str, stats: Callable[[], dict[str, float]]) -> None:
        """``stats``: the node's stats, read only when recording."""
        self.seq += 1
        self.recording.link(link_state, self.clock, stats)
        echo_send, echo_recv = self.clock.echo_fields()
        t_send = self.now()
        if self.gate is not None:
            self.gate.heartbeat_sent(t_send)
        self.pub().send(
            Heartbeat(
                seq=self.seq,
                t_send_ns=t_send,
                node="operator",
                state=link_state,
                echo_t_send_ns=echo_send,
                echo_t_recv_ns=echo_recv,
                session=self.session,
                echo_session=self.heard.session,
            )
        )
