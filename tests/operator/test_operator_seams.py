"""The operator node handed a clock and a capture link: driven without sockets or threads."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from common.clock import VirtualClock
from common.messages import Stimulus
from common.transport import CaptureLink
from operator_side.config import OperatorConfig
from operator_side.node import OperatorNode
from operator_side.servos.recording import RecordingServoBus


def _stimulus(seq: int, t_ns: int) -> Stimulus:
    return Stimulus(
        seq=seq,
        t_send_ns=t_ns,
        t_capture_ns=t_ns,
        frame_seq=seq,
        mode="direct",
        contact=True,
        stimulus=np.array([[0, 5, 0], [0, 5, 0], [0, 5, 0]], np.float32),
    )


def test_a_delivered_stimulus_moves_the_servos_in_virtual_time() -> None:
    clock = VirtualClock()
    link = CaptureLink()
    bus = RecordingServoBus()
    bus.connect()
    node = OperatorNode(OperatorConfig(), bus, now=clock, link=link)
    period = round(1e9 / node.config.renderer.control_rate_hz)
    link.deliver(_stimulus(1, clock()), clock())
    assert node.receive()
    assert node.last_stimulus is not None and node.last_stimulus.seq == 1
    node.control_step(clock(), period)
    first = node.written_goals
    assert first is not None and first != node.renderer.retract_goals
    clock.advance(period)
    node.control_step(clock(), period)  # still stepping toward the goal
    assert node.written_goals != first
    writes = node.counters["servo_writes"]
    node.rewrite_next()
    node.control_step(clock(), period)
    assert node.counters["servo_writes"] == writes + 1
    stale = round(node.config.link.stale_after_ms * 1e6) + 1
    clock.advance(stale)
    node.control_step(clock(), period)
    assert node.link_state == "stale"


def test_a_node_handed_a_link_refuses_to_run() -> None:
    node = OperatorNode(OperatorConfig(), RecordingServoBus(), link=CaptureLink())
    with pytest.raises(RuntimeError, match="handed a link"):
        node.run(threading.Event())
