"""One admission for every operator message: an unsigned link is a roster of one operator.

The arm is a MemoryArm behind the node's own device worker, so what the
tests read is what reached the driver. The signed path (a roster, the
lease) is exercised end to end in tests/fabric/test_fleet_fabric.py and
tests/robot/test_stop_latch.py.
"""

from __future__ import annotations

import contextlib
import itertools
import time

import pytest

from common.clocks.clock import now_ns
from common.wire.messages import COMMAND_ACTIONS, LEASE_ACTIONS, Command, Heartbeat
from common.wire.transport import CaptureLink
from robot_side.arm.memory import MemoryArm
from robot_side.node import RobotNode
from robot_side.node.config import RobotConfig
from robot_side.node.device_calls import DEVICE_CALLS

JOG = (0.02, 0.0, 0.0, 0.0, 0.0, 0.0)


def test_every_action_is_a_device_call_or_is_used_up_before_one() -> None:
    """A new action in the protocol needs a row in the table (or a reason to have none)."""
    # the lease's, the stop latch's and the assist's (an enable: the assist makes the calls)
    used_up = LEASE_ACTIONS | {"arm_resume", "arm_assist"}
    assert set(DEVICE_CALLS) | used_up == set(COMMAND_ACTIONS)
    assert not set(DEVICE_CALLS) & used_up


class Operator:
    """One unsigned operator talking to a node through a capture link, on the same clock."""

    def __init__(self, node: RobotNode, link: CaptureLink) -> None:
        self.node, self.link = node, link
        self.seq = itertools.count(1)

    def sync(self) -> None:
        """One heartbeat round trip: the robot knows our clock (offset 0) and acts on jogs."""
        t1 = now_ns() - 2_000_000  # the robot's heartbeat, as we echo it
        hb = Heartbeat(seq=1, t_send_ns=now_ns() - 1_000_000, node="operator", state="ok",
                       echo_t_send_ns=t1, echo_t_recv_ns=t1 + 500_000, session=7,
                       echo_session=self.node.session)  # fmt: skip
        self.link.deliver(hb, now_ns())
        self.node.receive(now_ns())
        assert self.node.clock.is_synced

    def send(self, action: str, **fields) -> None:
        cmd = Command(seq=next(self.seq), t_send_ns=now_ns(), action=action, session=7,
                      echo_session=self.node.session, **fields)  # fmt: skip
        self.link.deliver(cmd, now_ns())
        self.node.receive(now_ns())


def _until(check, timeout_s: float = 10.0) -> bool:
    """The arm's worker thread runs the call: wait for it (generous: a loaded machine)."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if check():
            return True
        time.sleep(0.005)
    return check()


@pytest.fixture
def rig():
    config = RobotConfig()
    config.render.mode = "direct"
    arm = MemoryArm()
    link = CaptureLink()
    node = RobotNode(config, None, arm=arm, link=link)
    with contextlib.ExitStack() as stack:
        arm.connect()
        stack.callback(arm.disconnect)
        node.workers.start(stack)
        operator = Operator(node, link)
        operator.sync()
        yield node, arm, operator


def test_the_one_operator_holds_control_and_passes_the_same_stop_latch(rig) -> None:
    node, arm, op = rig
    op.send("arm_jog", velocity=JOG)
    assert _until(lambda: len(arm.sent_jogs) == 1), "the operator's jog never reached the arm"
    op.send("arm_stop")
    assert node.stats()["arm_stop_latched"] == 1.0
    op.send("arm_jog", velocity=JOG)
    assert node.counters["commands_stop_latched"] == 1
    op.send("arm_resume")
    assert node.stats()["arm_stop_latched"] == 0.0
    op.send("arm_jog", velocity=JOG)
    assert _until(lambda: len(arm.sent_jogs) == 2), "the jog after the resume never moved it"
    assert node.counters["commands_received"] == 5


def test_a_lease_action_on_an_unsigned_link_is_counted_and_moves_nothing(rig) -> None:
    """The one operator always holds control: asking for it changes nothing, stops nothing."""
    node, arm, op = rig
    for action in sorted(LEASE_ACTIONS):
        op.send(action)
    assert node.counters["lease_actions_without_roster"] == len(LEASE_ACTIONS)
    op.send("gripper_open")  # behind them on the same path: this scene has no gripper
    assert node.counters["commands_rejected"] == 1
    time.sleep(0.2)  # anything posted to the arm's worker would have run by now
    assert arm.stops == 0 and not arm.sent_jogs


def test_a_stop_awaiting_proof_stops_and_holds_the_arm_until_the_holders_resume(rig) -> None:
    """A stop that does not echo this run (a replay, or a sender a beat behind) waits."""
    node, arm, op = rig
    op.send("arm_jog", velocity=JOG)
    assert _until(lambda: len(arm.sent_jogs) == 1)
    cmd = Command(seq=1, t_send_ns=now_ns(), action="arm_stop", session=8, echo_session=1)
    op.link.deliver(cmd, now_ns())  # another boot, echoing a run that is not this one
    node.receive(now_ns())
    assert _until(lambda: arm.stops == 1), "the waiting stop did not stop the arm"
    assert node.counters["arm_stops_pending"] == 1 and not node.desk.stop_latch.latched
    op.send("arm_jog", velocity=JOG)
    assert node.counters["commands_stop_pending"] == 1
    op.send("arm_resume")
    assert node.counters["arm_stops_pending_resumed"] == 1
    op.send("arm_jog", velocity=JOG)
    assert _until(lambda: len(arm.sent_jogs) == 2), "the jog after the resume never moved it"
