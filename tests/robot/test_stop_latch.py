"""The stop latch's admission rules, on a real robot node and real signed operator nodes.

Four roster keys on one robot (direct link, every command signed): a and b
controllers, an observer, a recorder. The arm is read from the UR simulator,
what each operator sees from its own node (the robot's heartbeat).
"""

from __future__ import annotations

import threading
import time
from contextlib import contextmanager

import numpy as np
import pytest
from tests_support import free_ports

from common.wire.signing import generate_key_files
from operator_side.node import OperatorNode
from operator_side.node.config import OperatorConfig
from operator_side.servos.in_memory import InMemoryServoBus
from robot_side.arm.sim import SimulatedArm
from robot_side.node import RobotNode
from robot_side.node.commands.stop_latch import StopLatch
from robot_side.node.config import RobotConfig
from robot_side.tactile.scripted import ScriptedTactileSensor

pytestmark = [pytest.mark.slow, pytest.mark.timeout(120)]

ROLES = {"a": "controller", "b": "controller", "obs": "observer", "rec": "recorder"}
JOG = (0.03, 0.0, 0.0, 0.0, 0.0, 0.0)


def test_the_rules_without_sockets():
    latch = StopLatch()
    assert latch.judge("arm_jog", holder=True) is None
    assert latch.judge("arm_stop", holder=False, role="recorder") == "arm_stops_refused_role"
    assert latch.judge("arm_stop", holder=False, role="observer") is None
    assert latch.apply("arm_stop", "obs", 0) and latch.latched and latch.by == "obs"
    assert latch.judge("arm_jog", holder=True) == "commands_stop_latched"
    assert latch.judge("arm_jog_end", holder=True) is None  # ends motion: never refused
    assert not latch.apply("arm_jog_end", "a", 1) and latch.latched
    assert latch.judge("arm_resume", holder=False, role="controller") == (
        "arm_resumes_refused_not_holder"
    )
    assert latch.judge("arm_jog", holder=False, role="controller") == "commands_not_controller"
    assert latch.judge("arm_resume", holder=True) is None
    assert latch.apply("arm_resume", "a", 2) and not latch.latched
    assert latch.judge("arm_jog", holder=True) is None


@pytest.fixture
def cell(tmp_path, quiet_gc):
    tel, cmd = (f"tcp://127.0.0.1:{p}" for p in free_ports(2))
    entries = []
    secrets = {}
    for name, role in ROLES.items():
        public, secrets[name] = generate_key_files(tmp_path, name)
        entries.append(
            f'[[operator]]\nname = "{name}"\nrole = "{role}"\n'
            f'signing_key = "{public.read_text().strip()}"\n'
        )
    roster = tmp_path / "roster.toml"
    roster.write_text("\n".join(entries))
    rc = RobotConfig()
    rc.render.mode = "mask_ground_truth"
    rc.link.telemetry_endpoint, rc.link.command_endpoint = tel, cmd
    rc.link.roster_file = roster
    arm = SimulatedArm()
    robot = RobotNode(rc, ScriptedTactileSensor(), arm=arm)
    operators = {}
    for name in ROLES:
        oc = OperatorConfig()
        oc.link.telemetry_endpoint, oc.link.command_endpoint = tel, cmd
        oc.link.signing_key_file = secrets[name]
        oc.link.request_control = name == "a"
        oc.link.observer_heartbeat_rate_hz = oc.link.heartbeat_rate_hz  # every clock synced fast
        operators[name] = OperatorNode(oc, InMemoryServoBus())
    stop = threading.Event()
    threads = [threading.Thread(target=robot.run, args=(stop,), daemon=True)]
    threads += [
        threading.Thread(target=o.run, args=(stop,), daemon=True) for o in operators.values()
    ]
    for t in threads:
        t.start()
    try:
        wait(lambda: arm.sim is not None and arm.is_connected, 30, "the simulated arm")
        wait(lambda: operators["a"].holds_lease, 30, "a's lease")
        time.sleep(1.0)  # every operator's clock offset known at the robot
        yield robot, arm, operators
    finally:
        stop.set()
        for t in threads:
            t.join(timeout=10)


def wait(cond, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.02)


def speed(arm: SimulatedArm) -> float:
    return float(np.linalg.norm(arm.sim.tcp_speed()[:3]))


@contextmanager
def jogging(node: OperatorNode):
    """``node`` sends a +x jog every 50 ms (a held key) for as long as the block runs."""
    done = threading.Event()

    def run() -> None:
        while not done.is_set():
            node.send_command("arm_jog", velocity=JOG)
            done.wait(0.05)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    try:
        yield
    finally:
        done.set()
        t.join(2)
        node.send_command("arm_jog_end")


def moves(arm: SimulatedArm, seconds: float) -> float:
    """Top linear speed the simulator shows over ``seconds``."""
    top, end = 0.0, time.monotonic() + seconds
    while time.monotonic() < end:
        top = max(top, speed(arm))
        time.sleep(0.01)
    return top


def all_see_latch(operators: dict[str, OperatorNode], latched: bool) -> None:
    wait(
        lambda: all(_says_latched(o) == latched for o in operators.values()),
        3,
        f"every operator to see the latch {'set' if latched else 'released'}",
    )


def test_a_stop_latches_for_everyone_and_only_the_holders_resume_releases_it(cell):
    robot, arm, ops = cell
    a, b, obs, rec = ops["a"], ops["b"], ops["obs"], ops["rec"]
    with jogging(a):
        wait(lambda: speed(arm) > 0.02, 5, "a's jog to move the arm")
        rec.send_command("arm_stop")  # a recorder is a machine: its stop is refused
        assert moves(arm, 0.5) > 0.02, "a recorder's stop stopped the arm"
        assert robot.stats()["arm_stops_refused_role"] >= 1

        obs.send_command("arm_stop")  # an observer may press STOP
        wait(lambda: speed(arm) < 1e-4, 1, "the observer's stop to stop the arm")
        all_see_latch(ops, True)
        assert moves(arm, 1.0) < 1e-4, "the holder's jogs moved a latched arm"
        assert robot.stats()["commands_stop_latched"] >= 10

        for other in (b, obs):  # nobody but the holder resumes
            other.send_command("arm_resume")
        a.send_command("arm_jog_end")  # nor does ending a jog
        assert moves(arm, 0.5) < 1e-4
        assert robot.stats()["arm_resumes_refused_not_holder"] >= 2
        assert robot.stats()["arm_stop_latched"] == 1.0

    # the lease goes to b: the latch stays, a (no longer holder) cannot resume, b can
    b.send_command("lease_request")
    wait(lambda: b.lease_pending is not None, 3, "b's request")
    a.send_command("lease_grant", grantee=b.signer.public)
    wait(lambda: b.holds_lease, 3, "b's lease")
    a.send_command("arm_resume")
    with jogging(b):
        assert moves(arm, 1.0) < 1e-4, "a hand-over released the latch"
        assert robot.stats()["arm_stop_latched"] == 1.0
        resume_as_a_user_does(robot, b)
        all_see_latch(ops, False)
        wait(lambda: speed(arm) > 0.02, 3, "b's jog to move the arm after its resume")
    stats = robot.stats()
    assert stats["arm_stops_latched"] == 1 and stats["arm_resumes"] == 1, stats


#: the robot's refusals of a command that came too late (a starved PC), not for who sent it
LATE = ("commands_stale", "commands_unsynced")
#: the holder went silent past the robot's deadman (a starved PC): the lease lapsed with it
EXPIRED = "lease_expired"


def resume_as_a_user_does(robot: RobotNode, node: OperatorNode, presses: int = 3) -> None:
    """``node`` presses resume until the robot releases the latch.

    A resume that waited on a starved PC past the commands' staleness limit is
    refused as late, and the page says so; its user presses again. A holder
    whose PC went silent past the robot's deadman lost the lease with it (the
    lease expires; the page says "no control"): its user asks for the lease
    again, then presses. A press is repeated only after the robot counted one
    of these: a resume lost or refused for any other reason fails here, with
    the robot's counters.
    """
    keys = ("arm_stop_latched", "arm_resumes", "arm_resumes_refused_not_holder", *LATE, EXPIRED)
    for _ in range(presses):
        before = robot.stats()
        if before.get(EXPIRED, 0) and robot.desk.lease.holder != node.signer.public:
            # nobody else asks: it is granted at once; a request that waited on a starved PC
            # past the commands' staleness is refused as late, and its user asks again
            deadline, ask_at = time.monotonic() + 3.0, 0.0
            while not node.holds_lease:
                assert time.monotonic() < deadline, "timed out waiting for the lease again"
                if time.monotonic() >= ask_at:
                    node.send_command("lease_request")
                    ask_at = time.monotonic() + 0.5
                time.sleep(0.02)
        node.send_command("arm_resume")
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline:
            now = robot.stats()
            if now["arm_stop_latched"] == 0.0:
                return
            if any(now.get(k, 0) > before.get(k, 0) for k in LATE) or (
                now.get(EXPIRED, 0) and robot.desk.lease.holder != node.signer.public
            ):
                time.sleep(0.2)  # refused as late, or the lease lapsed: the user sees it
                break
            time.sleep(0.02)
        else:
            raise AssertionError(
                f"the holder's resume neither released the latch nor came late: "
                f"{ {k: now.get(k) for k in keys} } (before: { {k: before.get(k) for k in keys} })"
            )
    raise AssertionError(
        f"{presses} resumes, each late: { {k: robot.stats().get(k) for k in keys} }"
    )


def _says_latched(operator) -> bool:
    """Whether the robot's newest heartbeat, as this operator heard it, says a STOP holds."""
    return bool(operator.arrivals.robot_stats.get("arm_stop_latched"))
