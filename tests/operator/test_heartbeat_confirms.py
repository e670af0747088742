"""A robot heartbeat confirms the palm's stimulus by the change it names, keyframes lost or not."""

from __future__ import annotations

import numpy as np

from common.clocks.clock import VirtualClock
from common.wire.messages import Heartbeat, Stimulus
from common.wire.transport import CaptureLink
from operator_side.node import OperatorNode
from operator_side.node.config import OperatorConfig
from operator_side.servos.in_memory import InMemoryServoBus

SESSION = 7
CELLS = np.array([[0, 5, 0], [0, 5, 0], [0, 5, 0]], np.float32)
OTHER = np.array([[5, 0, 0], [0, 5, 0], [0, 0, 5]], np.float32)


def _stimulus(seq: int, t_ns: int, cells: np.ndarray, keyframe: bool) -> Stimulus:
    return Stimulus(seq=seq, t_send_ns=t_ns, t_capture_ns=t_ns, frame_seq=seq, mode="direct",
                    contact=True, stimulus=cells, keyframe=keyframe, session=SESSION)  # fmt: skip


def _heartbeat(seq: int, t_ns: int, names: int, session: int = SESSION) -> Heartbeat:
    return Heartbeat(seq=seq, t_send_ns=t_ns, node="robot", state="ok", stimulus_seq=names,
                     t_capture_ns=t_ns, session=session)  # fmt: skip


class Rig:
    def __init__(self) -> None:
        self.clock = VirtualClock()
        self.link = CaptureLink()
        bus = InMemoryServoBus()
        bus.connect()
        self.node = OperatorNode(OperatorConfig(), bus, now=self.clock, link=self.link)
        self.period = round(1e9 / self.node.config.renderer.palm_step_rate_hz)
        self.stale_ns = round(self.node.config.link.stale_after_ms * 1e6)
        self._hb = 0

    def deliver(self, msg: Stimulus | Heartbeat) -> None:
        self.link.deliver(msg, self.clock())
        self.node.receive()
        self.node.palm_step(self.clock(), self.period)

    def change_then_keyframe(self, keyframe_seq: int = 2, cells: np.ndarray = CELLS) -> None:
        """Change 1 (``CELLS``), then 25 ms later a keyframe with ``cells``."""
        self.deliver(_stimulus(1, self.clock(), CELLS, keyframe=False))
        self.clock.advance(25_000_000)
        self.deliver(_stimulus(keyframe_seq, self.clock(), cells, keyframe=True))

    def heartbeats_for(self, duration_ns: int, names: int, **kw) -> None:
        """A robot heartbeat every 50 ms naming ``names``, the palm stepped between them."""
        end = self.clock() + duration_ns
        while self.clock() < end:
            self.clock.advance(50_000_000)
            self._hb += 1
            self.deliver(_heartbeat(self._hb, self.clock(), names, **kw))


def test_heartbeats_naming_the_change_keep_the_palm_on_while_its_keyframes_are_lost():
    rig = Rig()
    rig.change_then_keyframe()
    assert rig.node.link_state == "ok"
    # keyframes 3, 4, ... lost; the heartbeats name change 1, whose cells the palm shows
    rig.heartbeats_for(4 * rig.stale_ns, names=1)
    assert rig.node.link_state == "ok"


def test_a_heartbeat_naming_a_change_the_palm_never_got_confirms_nothing():
    rig = Rig()
    # change 2 (other cells) lost; its keyframe 3 arrives: the palm shows change 2's cells
    # without knowing the change's number, so only keyframes confirm it
    rig.change_then_keyframe(keyframe_seq=3, cells=OTHER)
    rig.heartbeats_for(2 * rig.stale_ns, names=2)
    assert rig.node.link_state == "stale"


def test_a_heartbeat_of_another_run_naming_the_same_number_confirms_nothing():
    rig = Rig()
    rig.change_then_keyframe()
    rig.heartbeats_for(2 * rig.stale_ns, names=1, session=SESSION + 1)
    assert rig.node.link_state == "stale"


def test_without_heartbeats_the_palm_lifts_once_the_keyframes_stop():
    rig = Rig()
    rig.deliver(_stimulus(1, rig.clock(), CELLS, keyframe=False))
    rig.clock.advance(rig.stale_ns + rig.period)
    rig.node.palm_step(rig.clock(), rig.period)
    assert rig.node.link_state == "stale"
