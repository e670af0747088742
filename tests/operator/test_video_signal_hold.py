"""A video offer waits until the robot is known to hear the operator: sent once, it must arrive."""

from __future__ import annotations

from operator_side.node import VIDEO_HOLD_NS, OperatorNode
from operator_side.node.config import OperatorConfig
from operator_side.servos.in_memory import InMemoryServoBus


class _Wire:
    def __init__(self) -> None:
        self.sent: list = []

    def send(self, msg) -> bytes:
        self.sent.append(msg)
        return b""


def _node() -> tuple[OperatorNode, _Wire]:
    node = OperatorNode(OperatorConfig(), InMemoryServoBus())
    wire = _Wire()
    node.pub = wire
    return node, wire


def test_an_offer_before_the_robot_echoed_us_waits_for_the_echo():
    node, wire = _node()
    node.send_video_signal("offer", viewer=7, sdp="v=0")
    node.send_video_signal("bye", viewer=7)
    node.flush_commands(1_000_000_000)
    assert wire.sent == []  # the command link may not carry yet: an offer lost is never answered
    node.clock.add_sample(1_000, 2_000, 3_000, 4_000)  # the robot echoed a heartbeat of ours
    node.flush_commands(1_100_000_000)
    assert [(m.kind, m.viewer) for m in wire.sent] == [("offer", 7), ("bye", 7)]  # in order
    node.send_video_signal("offer", viewer=8, sdp="v=0")
    node.flush_commands(1_200_000_000)
    assert [m.viewer for m in wire.sent] == [7, 7, 8]  # synced: at once


def test_a_robot_that_never_echoes_gets_the_offer_after_the_hold():
    node, wire = _node()
    node.send_video_signal("offer", viewer=7, sdp="v=0")
    node.flush_commands(0)
    node.flush_commands(VIDEO_HOLD_NS - 1)
    assert wire.sent == []
    node.flush_commands(VIDEO_HOLD_NS)
    assert [m.kind for m in wire.sent] == ["offer"]
