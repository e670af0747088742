"""Messages over the 16 KiB limit: ZeroMQ drops them before the codec, with the connection.

The sockets' MAXMSGSIZE makes libzmq close the connection that carried an
oversized frame (a protocol error), so nothing is read, allocated or
counted. On the robot's bound command socket that costs only the sender's
own connection. On the operator's telemetry socket it is the one link to
the robot: the palm must lift off (the stimulus goes stale) and the node
keep running; test_fuzz_found.py checks that it reconnects.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from fuzz_rigs import OperatorRig, RobotRig, arm_violations, wait_for

from common.wire.codec import MAX_MESSAGE_BYTES, encode
from common.wire.messages import Command, Heartbeat

SIZES = [MAX_MESSAGE_BYTES + 1, MAX_MESSAGE_BYTES + 100, 100_000, 4_000_000]


def _oversized(n: int) -> bytes:
    body = encode(Heartbeat(seq=1, t_send_ns=1, node="operator", state="ok"))
    return body + b"\x00" * (n - len(body))


@pytest.fixture
def robot():
    r = RobotRig()
    r.start()
    yield r
    r.close()


def test_oversized_commands_cost_only_the_senders_connection(robot):
    for n in SIZES:
        robot.evil.send(_oversized(n))  # not counted in robot.sent: it is never received
        time.sleep(0.05)
    # the good operator is untouched: its commands keep arriving and being applied
    for level in (5, 25):
        want = robot.gripper.levels.position(level)

        def applied(want: int = want) -> bool:
            cmds = robot.gripper.commands  # a copy each time
            return bool(cmds) and cmds[-1][0] == want

        # a command the robot reads after its age limit is refused as stale (a loaded
        # machine can hold the read up that long): a fresh one is what an operator sends
        for _ in range(3):
            robot.command("gripper_close", grip_level=level)
            assert robot.sync(5)
            if wait_for(applied, 1):
                break
        assert applied()
    assert robot.alive()
    # the oversized ones (not in sent) were never read; a heartbeat may be on its way meanwhile
    assert wait_for(lambda: robot.received() == robot.sent, 1)
    # the evil connection is re-made by its own side (a PUB reconnects), and is heard again
    seq = iter(range(1, 10_000))

    def evil_heard() -> bool:
        before = len(robot.arm.sent_jogs)
        jog = Command(
            seq=next(seq),
            t_send_ns=time.monotonic_ns(),
            action="arm_jog",
            velocity=(0.01, 0, 0, 0, 0, 0),
            session=99,
            echo_session=robot.robot_session,  # of this robot run, as an operator's is
        )
        robot.evil.send(encode(jog))
        time.sleep(0.05)
        return len(robot.arm.sent_jogs) > before

    assert wait_for(evil_heard, 5, step_s=0.05)
    assert arm_violations(robot.arm) == []


@pytest.fixture
def operator():
    r = OperatorRig()
    r.start()
    yield r
    r.close()


def test_an_oversized_telemetry_frame_lifts_the_palm_and_nothing_worse(operator):
    rig = operator
    msg = rig.show(6)
    target = rig.node.renderer.target_counts(msg.stimulus)
    assert wait_for(lambda: rig.goal_reached(target), 5), "the good stimulus never arrived"
    with rig._send_lock:
        rig.pub.send(_oversized(SIZES[0]))
    retract = rig.node.renderer.retract_counts
    # the link goes stale within stale_after_ms and the rate limiter walks every linkage off
    assert wait_for(lambda: rig.node.link_state != "ok", 2)
    assert wait_for(lambda: rig.goal_reached(retract), 5)
    assert rig.alive()
    assert rig.servo_violations() == []
    assert np.array_equal(rig.node.written_goals, retract)
