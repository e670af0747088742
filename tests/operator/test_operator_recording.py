"""A received stimulus is recorded as the bytes that crossed the link, not encoded again.

Through a relay the robot's stimuli carry its name and its signature; a
re-encoding would drop both, so a replay could neither tell whose stream it
was nor check it. Real sockets: the robot's publisher, the node's subscriber.
"""

from __future__ import annotations

import time

import numpy as np
import zmq

from common.wire.codec import decode, encode
from common.wire.messages import Stimulus
from common.wire.signing import Signer
from common.wire.transport import Link, Publisher, Subscriber
from operator_side.node import OperatorNode
from operator_side.node.config import OperatorConfig
from operator_side.servos.in_memory import InMemoryServoBus
from tests.tests_support import free_ports


class Kept:
    """A recorder that keeps each record."""

    def __init__(self) -> None:
        self.records: list[tuple[str, int, dict]] = []

    def write(self, channel: str, t_ns: int, record: dict) -> None:
        self.records.append((channel, t_ns, record))


def test_a_named_signed_stimulus_is_recorded_as_it_arrived() -> None:
    endpoint = f"tcp://127.0.0.1:{free_ports(1)[0]}"
    ctx = zmq.Context()
    robot = Publisher(ctx, endpoint, bind=True, name=b"cell1", signer=Signer.generate())
    sub = Subscriber(ctx, endpoint, bind=False, name="operator telemetry")
    recorder = Kept()
    node = OperatorNode(OperatorConfig(), InMemoryServoBus(), recorder=recorder, link=Link(sub=sub))
    try:
        sent: list[bytes] = []
        deadline = time.monotonic() + 10
        while not node.receive():  # PUB/SUB: the first messages go before the subscription
            assert time.monotonic() < deadline, (sub.received, dict(sub.rejected), node.counters)
            t = time.monotonic_ns()
            stim = Stimulus(
                seq=len(sent) + 1,
                t_send_ns=t,
                t_capture_ns=t,
                frame_seq=len(sent) + 1,
                mode="direct",
                contact=True,
                stimulus=np.array([[0, 5, 0], [0, 5, 0], [0, 5, 0]], np.float32),
            )
            sent.append(robot.send(stim))
            sub.poll(0.05)
        stimuli = [r for channel, _, r in recorder.records if channel == "operator/stimulus"]
        assert len(stimuli) == 1
        wire = stimuli[0]["wire"]
        assert wire in sent  # byte for byte: the robot's name and signature kept
        msg = decode(wire)
        assert msg.signer is not None and wire != encode(msg)
    finally:
        sub.close()
        robot.close()
        ctx.term()
