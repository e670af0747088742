"""The robot's command path under load, seen from outside: the wire, the arm and gripper simulators.

The robot node runs as its own process, as deployed, with its real UR driver
(ur-rtde) against the UR simulator and its real Robotiq socket driver
against the gripper simulator, both served from this test; the operators
here are raw clients written from docs/protocol.md.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
import zmq
from tests_support import ProtocolOperator

from common.clock import now_ns
from common.codec import encode
from common.messages import Heartbeat, Stimulus
from common.transport import Publisher, Subscriber
from deploy.bench.command_path import PUBLISH_HZ, RobotUnderCommands
from robot_side.gripper.base import GripLevels

N_FLOOD = 100_000


@pytest.fixture
def rig(tmp_path: Path):
    with RobotUnderCommands(tmp_path) as r:
        yield r


def test_a_flood_of_jogs_neither_starves_the_palm_nor_outlives_the_sender(rig):
    t0 = now_ns()
    time.sleep(2.0)
    normal = rig.stimulus_rate(t0, now_ns())
    assert normal > 0.8 * PUBLISH_HZ, f"the scripted grasp gave only {normal:.0f} stimuli/s"
    report = rig.flood(N_FLOOD)
    t_first, t_last = report["t_first_ns"], report["t_last_ns"]
    time.sleep(2.5)  # let the backlog in the kernel's and ZeroMQ's queues age out

    # the operator's jog moved the arm before the flood: the test can see motion at all
    assert rig.arm.moving_between(report["t_start_ns"], t_first, above=0.01), "no pre-flood jog"
    # the arm is still 400 ms after the sender's last send, and stays still
    late = rig.arm.moving_between(t_last + 400_000_000, now_ns())
    assert not late, f"the arm moved {(late[-1] - t_last) / 1e6:.0f} ms after the last send"
    # the palm kept its stimuli while the flood and its backlog were read
    during = rig.stimulus_rate(t_first, t_last + 2_000_000_000)
    assert during >= 0.9 * normal, f"stimuli at {during / normal:.2f} of normal during the flood"
    stats = rig.telemetry.robot_stats()
    assert stats.get("commands_stale", 0) + stats.get("commands_superseded", 0) > 0
    print(
        f"\nflood: {N_FLOOD} jogs in {(t_last - t_first) / 1e9:.2f} s; stimuli {during:.1f}/s "
        f"against {normal:.1f}/s; counters {stats}"
    )


def test_jog_and_stop_repeated_never_stall_the_telemetry(rig):
    telemetry, tel, cmd = rig.telemetry, rig.telemetry_endpoint, rig.command_endpoint
    ctx = zmq.Context()
    op = ProtocolOperator(
        Subscriber(ctx, tel, bind=False), Publisher(ctx, cmd, bind=False), session=11
    )
    try:
        op.sync()
        # the machine's own stalls, with no command in flight: what the command path must not add to
        i0 = now_ns()
        op.pump(3.0)
        i1 = now_ns()
        jogs = [(0.1, 0.0, 0.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0, 0.0, 0.5)]
        t0 = now_ns()
        cycles = 0
        while now_ns() - t0 < 10e9:
            velocity = jogs[cycles % 2]
            for _ in range(4):  # a held key: renewed every 50 ms
                op.command("arm_jog", velocity=velocity)
                op.pump(0.05)
            op.command("arm_stop")
            op.pump(0.1)
            cycles += 1
        t1 = now_ns()
        op.pump(0.2)
    finally:
        op.sub.close()
        op.pub.close()
        ctx.term()

    # gaps by the robot's own send stamps: what it did, not when this process got round to reading
    def gap(kind: type, a: int, b: int) -> float:
        return float(max(np.diff(sorted(telemetry.sent_times(kind, a, b))))) / 1e6

    stim_gap, beat_gap = gap(Stimulus, t0, t1), gap(Heartbeat, t0, t1)
    idle_stim, idle_beat = gap(Stimulus, i0, i1), gap(Heartbeat, i0, i1)
    received_gap = float(max(np.diff(telemetry.times(Stimulus, t0, t1)))) / 1e6
    period = 1000 / PUBLISH_HZ
    assert rig.arm.moving_between(t0, t1, above=0.01), "the jogs never moved the arm"
    # two frame periods, or on a machine that stalls the node by itself (a loaded shared VM),
    # no more than its own stalls plus one period: a blocking stop takes hundreds of ms
    assert stim_gap <= max(2 * period, idle_stim + period), (
        f"a {stim_gap:.1f} ms gap in the stimuli (idle: {idle_stim:.1f} ms)"
    )
    assert beat_gap <= max(70.0, idle_beat + period), (
        f"a {beat_gap:.1f} ms gap between heartbeats (idle: {idle_beat:.1f} ms)"
    )
    assert telemetry.robot_stats().get("deadman_trips", 0) == 0
    print(
        f"\n{cycles} jog+stop cycles: stimulus gap {stim_gap:.1f} ms (idle {idle_stim:.1f}), "
        f"heartbeat gap {beat_gap:.1f} ms (idle {idle_beat:.1f}); "
        f"largest gap as received here {received_gap:.1f} ms"
    )


def test_a_replayed_command_is_refused_and_counted(rig):
    telemetry, tel, cmd = rig.telemetry, rig.telemetry_endpoint, rig.command_endpoint
    ctx = zmq.Context()
    op = ProtocolOperator(
        Subscriber(ctx, tel, bind=False), Publisher(ctx, cmd, bind=False), session=21
    )
    replayer = Publisher(ctx, cmd, bind=False)  # a connection of its own
    model = rig.gripper_sim.model

    def requested() -> int:
        return model.read()["PRE"]

    def settle(want: int) -> bool:
        deadline = time.monotonic() + 3
        while time.monotonic() < deadline:
            op.pump(0.02)
            if requested() == want:
                return True
        return False

    try:
        op.sync()
        closed = GripLevels().position(20)  # the robot's default grip levels
        op.command("gripper_open")
        assert settle(0)
        # within the freshness window: close, open, then the captured close again
        captured = encode(op.command("gripper_close", grip_level=20))
        op.command("gripper_open")
        replayer.send_raw(captured)
        op.pump(0.5)
        assert requested() == 0, "a replayed close reached the gripper"
        # long after: the same bytes from the new connection are stale
        op.pump(1.0)
        replayer.send_raw(captured)
        op.pump(0.5)
        assert requested() == 0, "an old close reached the gripper"
        # and a fresh one from the real session still works
        op.command("gripper_close", grip_level=20)
        assert settle(closed)
        op.pump(0.2)
    finally:
        for sock in (op.sub, op.pub, replayer):
            sock.close()
        ctx.term()
    stats = telemetry.robot_stats()
    # both replays: seq and send time did not increase in the session (the late one is stale too)
    assert stats.get("commands_replayed", 0) >= 2
