"""A lift-off is the palm leaving a fresh stimulus, not a first stimulus that came in stale."""

from __future__ import annotations

import numpy as np

from common.clocks.clock import VirtualClock
from common.wire.messages import Stimulus
from common.wire.transport import CaptureLink
from operator_side.node import OperatorNode
from operator_side.node.config import OperatorConfig
from operator_side.servos.in_memory import InMemoryServoBus

CELLS = np.array([[0, 5, 0], [0, 5, 0], [0, 5, 0]], np.float32)


def _stimulus(seq: int, t_ns: int) -> Stimulus:
    return Stimulus(seq=seq, t_send_ns=t_ns, t_capture_ns=t_ns, frame_seq=seq, mode="direct",
                    contact=True, stimulus=CELLS, keyframe=False, session=7)  # fmt: skip


def test_only_leaving_a_fresh_stimulus_counts_as_a_lift_off():
    clock, link, bus = VirtualClock(), CaptureLink(), InMemoryServoBus()
    bus.connect()
    node = OperatorNode(OperatorConfig(), bus, now=clock, link=link)
    period = round(1e9 / node.config.renderer.palm_step_rate_hz)
    stale_ns = round(node.config.link.stale_after_ms * 1e6)

    # the first stimulus is read only after it went stale (a node starved at its start):
    # the palm was never on, so nothing lifted
    link.deliver(_stimulus(1, clock()), clock())
    node.receive()
    clock.advance(2 * stale_ns)
    node.palm_step(clock(), period)
    assert node.link_state == "stale"
    assert node.counters["lift_offs"] == 0

    # a fresh one puts the palm on; its silence past the staleness limit lifts it: one lift-off
    link.deliver(_stimulus(2, clock()), clock())
    node.receive()
    node.palm_step(clock(), period)
    assert node.link_state == "ok"
    clock.advance(stale_ns + period)
    node.palm_step(clock(), period)
    assert node.link_state == "stale"
    assert node.counters["lift_offs"] == 1
