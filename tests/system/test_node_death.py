"""The arm stops and the gripper holds whoever dies: kill -9 and SIGSTOP of the robot node.

The robot node runs as its own process, as deployed, with its real ur-rtde and
Robotiq socket drivers; the UR driver in the node's arm process (docs/arm.md,
The arm process). The UR simulator runs in a process of its own (not the
node's child, which would die with it) and the gripper simulator in this
test's process. An operator written from docs/protocol.md holds the pipette
and jogs at 0.03 m/s; the node is then killed or frozen mid-jog. ur-rtde's own
receive interface in this process reads when the controller has the arm
still. A killed node's arm process stops the arm at once (its stdin closes);
a frozen node's jog ends at its deadline in the arm process, whose keep-alive
goes on: the controller's watchdog never has to trip, and no reconnect follows.
"""

from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np
import pytest
import zmq
from tests_support import ProtocolOperator

from common.wire.transport import Publisher, Subscriber
from harness.bench.command_path import RobotUnderCommands

JOG_SPEED_M_S = 0.03
#: kill or freeze to an arm at rest, read by the controller (issue 25's budget)
STOP_BUDGET_S = 0.4
TRIALS = 3  # each about 2.5 s; the worst of three is held to the budget (docs/arm.md: runs of 10)
GRIP_LEVEL = 25

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("quiet_gc")]


class ControllerReader:
    """ur-rtde's receive interface in this process: the controller's view, whoever dies."""

    def __init__(self, host: str) -> None:
        import rtde_receive

        variables = ["timestamp", "actual_TCP_speed", "robot_status_bits"]
        self.rtde = rtde_receive.RTDEReceiveInterface(host, 500.0, variables)

    def speed(self) -> float:
        return float(np.linalg.norm(self.rtde.getActualTCPSpeed()[:3]))

    def still_after(self, t0: float, timeout_s: float = 3.0) -> float:
        """Seconds from ``t0`` (monotonic) until the controller reports the TCP at rest."""
        deadline = t0 + timeout_s
        while self.speed() > 0.0:
            if time.monotonic() > deadline:
                return float("inf")
            time.sleep(0.0005)
        return time.monotonic() - t0

    def moved_during(self, seconds: float) -> float:
        """Fastest TCP speed (m/s) seen over the next ``seconds``."""
        end, fastest = time.monotonic() + seconds, 0.0
        while time.monotonic() < end:
            fastest = max(fastest, self.speed())
            time.sleep(0.002)
        return fastest


class GripperLog:
    """The gripper simulator's registers sampled at 200 Hz: did it ever open or re-activate?"""

    def __init__(self, model) -> None:
        self.model = model
        self.samples: list[dict[str, int]] = []
        self._quit = threading.Event()
        self._thread = threading.Thread(target=self._run, name="gripper-log", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._quit.wait(0.005):
            self.samples.append(self.model.read())

    def close(self) -> None:
        self._quit.set()
        self._thread.join(2)


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    with RobotUnderCommands(tmp_path_factory.mktemp("node-death")) as r:
        reader = ControllerReader(r.arm_sim.host)
        r.reader = reader
        try:
            yield r
        finally:
            del r.reader, reader  # ur-rtde's destructor disconnects, before the simulator stops


@pytest.fixture
def operator(rig):
    ctx = zmq.Context()
    op = ProtocolOperator(
        Subscriber(ctx, rig.telemetry_endpoint, bind=False),
        Publisher(ctx, rig.command_endpoint, bind=False),
        session=int(time.monotonic()) & 0xFFFF,
    )
    op.sync()
    yield op
    op.sub.close()
    op.pub.close()
    ctx.term()


def _holding(rig, op: ProtocolOperator) -> dict[str, int]:
    """Close the gripper on the pipette through the node; its registers once it holds."""
    deadline = time.monotonic() + 10
    model = rig.gripper_sim.model
    resend = 0.0
    while not (model.read()["OBJ"] in (2, 3) and model.read()["PRE"] > 0):
        assert time.monotonic() < deadline, f"the gripper never closed: {model.read()}"
        if time.monotonic() >= resend:  # as the operator node resends an unconfirmed close
            op.command("gripper_close", grip_level=GRIP_LEVEL)
            resend = time.monotonic() + 1.0
        op.pump(0.05)
    return model.read()


def _jog_until_moving(rig, op: ProtocolOperator, direction: float) -> None:
    """A held jog key (renewed every 50 ms) until the controller moves at the jog speed."""
    velocity = [direction * JOG_SPEED_M_S, 0.0, 0.0, 0.0, 0.0, 0.0]
    deadline, steady = time.monotonic() + 15, 0
    while steady < 3:  # a few renewals at full speed: the steady jog of issue 25
        op.command("arm_jog", velocity=velocity)
        op.pump(0.05)
        steady = steady + 1 if abs(rig.reader.speed() - JOG_SPEED_M_S) < 1e-4 else 0
        assert time.monotonic() < deadline, (
            f"the jog never reached {JOG_SPEED_M_S} m/s (at {rig.reader.speed():.4f}); "
            f"robot log:\n{rig.log.read_text()[-3000:]}"
        )


def _still_after_signal(rig, sig: int, trial: int) -> float:
    """Send ``sig`` to the node mid-jog; seconds until the controller has the arm still."""
    t = time.monotonic()
    os.kill(rig.proc.pid, sig)
    took = rig.reader.still_after(t)
    assert took < float("inf"), (
        f"trial {trial}: the arm still moves at {rig.reader.speed():.3f} m/s 3 s after "
        f"{signal.Signals(sig).name} of the robot node: nothing on the controller stops it"
    )
    return took


def _assert_gripper_held(log: GripperLog, held: dict[str, int]) -> None:
    opened = [s for s in log.samples if s["POS"] < held["POS"] - 2 or s["PRE"] != held["PRE"]]
    assert not opened, f"the gripper moved from {held}: first {opened[0]}"
    assert all(s["STA"] == 3 and s["ACT"] == 1 for s in log.samples), "it was re-activated"


def _summary(times: list[float]) -> str:
    ms = np.array(times) * 1000
    return f"min {ms.min():.0f} / median {np.median(ms):.0f} / max {ms.max():.0f} ms"


def test_kill_9_mid_jog_the_arm_process_stops_the_arm_and_the_gripper_holds(rig, operator):
    held = _holding(rig, operator)
    log = GripperLog(rig.gripper_sim.model)
    stop_s: list[float] = []
    trips_before = rig.arm_sim.stats()["watchdog_trips"]
    try:
        for trial in range(TRIALS):
            _jog_until_moving(rig, operator, 1.0 if trial % 2 == 0 else -1.0)
            stop_s.append(_still_after_signal(rig, signal.SIGKILL, trial))
            rig.proc.wait(5)
            # nothing of the dead node's moves the arm again, and a new node (with a new arm
            # process) starts the gripper as it finds it
            assert rig.reader.moved_during(0.2) == 0.0, f"trial {trial}: the arm moved again"
            rig.start_node()
            operator.sync()
    finally:
        log.close()
    print(f"\nkill -9 mid-jog to still ({TRIALS} trials): {_summary(stop_s)}")
    late = [f"{s * 1000:.0f}" for s in stop_s if s > STOP_BUDGET_S]
    assert not late, f"still later than {STOP_BUDGET_S * 1000:.0f} ms after kill -9: {late} ms"
    # the arm process stopped the arm and ended its script: the controller never had to
    assert rig.arm_sim.stats()["watchdog_trips"] == trips_before, "the arm process left it"
    _assert_gripper_held(log, held)


def test_sigstop_mid_jog_the_arm_process_stops_the_arm_and_sigcont_goes_on(rig, operator):
    held = _holding(rig, operator)
    log = GripperLog(rig.gripper_sim.model)
    stop_s: list[float] = []
    reconnects = rig.telemetry.robot_stats().get("arm_reconnects", 0.0)
    try:
        for trial in range(TRIALS):
            direction = 1.0 if trial % 2 == 0 else -1.0
            _jog_until_moving(rig, operator, direction)
            try:
                stop_s.append(_still_after_signal(rig, signal.SIGSTOP, trial))
                # the operator holds the key a while longer, then lets go: what the frozen
                # node finds queued at SIGCONT is stale and must move nothing
                for _ in range(4):
                    operator.command("arm_jog", velocity=[direction * JOG_SPEED_M_S, 0, 0, 0, 0, 0])
                    operator.pump(0.05)
                operator.pump(0.4)
            finally:
                os.kill(rig.proc.pid, signal.SIGCONT)
            operator.pump(0.3)
            assert rig.reader.moved_during(0.5) == 0.0, f"trial {trial}: moved after SIGCONT"
            # the node goes on with the same control script and jogs again
            _jog_until_moving(rig, operator, -direction)
            operator.command("arm_jog_end")  # a released key: an arm_stop would latch the arm
            assert rig.reader.still_after(time.monotonic()) < STOP_BUDGET_S
    finally:
        log.close()
    print(f"\nSIGSTOP mid-jog to still ({TRIALS} trials): {_summary(stop_s)}")
    late = [f"{s * 1000:.0f}" for s in stop_s if s > STOP_BUDGET_S]
    assert not late, f"still later than {STOP_BUDGET_S * 1000:.0f} ms after SIGSTOP: {late} ms"
    # the keep-alive ran on in the arm process: no watchdog trip, so no reconnect
    assert rig.telemetry.robot_stats()["arm_reconnects"] == reconnects, (
        "the controller's watchdog tripped while the arm process kicked on (robot log, with "
        f"the arm process's):\n{rig.log.read_text()[-6000:]}"
    )
    assert rig.proc.poll() is None, "the node died of its freeze"
    _assert_gripper_held(log, held)
