"""The assist, held from real signed operator nodes, seen on the UR simulator.

A robot node (SimulatedArm: the real ur-rtde driver against the UR
simulator) feels one scripted grasp for as long as the test runs, so the
assist re-grasps until it gives up: every motion it makes is one a wrong
pattern asks for. Two controllers on the roster: ``a`` holds the lease,
``b`` does not. What the tests read is the arm on the simulator and the
robot's heartbeat as ``a``'s node receives it.
"""

from __future__ import annotations

import threading
import time
from contextlib import contextmanager

import numpy as np
import pytest
from tests_support import free_ports, wait_until

from common.rotation import rotvec_to_matrix
from common.tactile.contract import classes_of
from common.tactile.synthetic import GeneratorParams, offset_direction
from common.wire.signing import generate_key_files
from harness.faults.matrix import ARM_STILL_BUDGET_S, STILL_M_S
from operator_side.node import OperatorNode
from operator_side.node.config import OperatorConfig
from operator_side.servos.in_memory import InMemoryServoBus
from robot_side.arm.sim import SimulatedArm
from robot_side.node import RobotNode
from robot_side.node.assist import PHASE_CODES
from robot_side.node.config import RobotConfig
from robot_side.perception.band import measure_band
from robot_side.tactile.script import GraspScript, GraspStep
from robot_side.tactile.scripted import ScriptedTactileConfig, ScriptedTactileSensor

pytestmark = [pytest.mark.slow, pytest.mark.timeout(180)]

#: below this the wrist counts as still (rad/s)
STILL_RAD_S = 0.005
#: the operator's enable, refreshed as a held jog key is
ENABLE_PERIOD_S = 0.05
#: 90 deg left: a shift of the pad centre alone; 45 deg left: a shift and a turn
SHIFT_ONLY, SHIFT_AND_TURN = 7, 4


def wait(cond, timeout_s: float, what: str) -> None:
    assert wait_until(cond, timeout_s, period_s=0.01), f"timed out waiting for {what}"


def still(arm: SimulatedArm) -> bool:
    v = arm.sim.tcp_speed()
    return float(np.linalg.norm(v[:3])) < STILL_M_S and float(np.linalg.norm(v[3:])) < STILL_RAD_S


def moving(arm: SimulatedArm) -> bool:
    v = arm.sim.tcp_speed()
    return float(np.linalg.norm(v[:3])) > 0.002 or float(np.linalg.norm(v[3:])) > 0.05


def phase(node: OperatorNode) -> float | None:
    return node.snapshot().robot_stats.get("assist_phase")


@contextmanager
def holding(node: OperatorNode):
    """``node`` holds the assist (an enable every 50 ms) while the block runs; then lets go."""
    done = threading.Event()
    sent: list[float] = []

    def run() -> None:
        while not done.is_set():
            node.send_command("arm_assist")
            sent.append(time.monotonic())
            done.wait(ENABLE_PERIOD_S)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    try:
        yield sent
    finally:
        done.set()
        t.join(2)


class ListRecorder:
    """What the node records, kept in order (the node writes from its loop and its workers)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.records: list[tuple[str, dict]] = []

    def write(self, channel: str, t_ns: int, record: dict) -> None:
        with self.lock:
            self.records.append((channel, dict(record)))

    def channel(self, name: str) -> list[dict]:
        with self.lock:
            return [r for c, r in self.records if c == name]


def _cell(tmp_path, pattern: int, box_face_mm: float | None, side_offset_mm: float | None):
    """(robot, arm, {"a": ..., "b": ...}, stop event, threads); the arm started, a holding."""
    tel, cmd = (f"tcp://127.0.0.1:{p}" for p in free_ports(2))
    entries, secrets = [], {}
    for name in ("a", "b"):
        public, secrets[name] = generate_key_files(tmp_path, name)
        entries.append(
            f'[[operator]]\nname = "{name}"\nrole = "controller"\n'
            f'signing_key = "{public.read_text().strip()}"\n'
        )
    roster = tmp_path / "roster.toml"
    roster.write_text("\n".join(entries))
    rc = RobotConfig()
    rc.render.mode = "mask_ground_truth"  # the recognised pattern is the scripted one
    rc.link.telemetry_endpoint, rc.link.command_endpoint = tel, cmd
    rc.link.roster_file = roster
    rc.assist.box_margin_m = 0.0  # its targets may reach the face: the arm's clipping must hold
    rc.assist.settle_ms = 150.0
    rc.assist.release_ms = 100.0
    grasp = GraspStep(pattern=pattern, grip_level=16, ramp_s=0.2, hold_s=3600.0)
    generator = GeneratorParams()
    if side_offset_mm is not None:  # the pipette this far off the pad centre, give or take 0.3
        generator = GeneratorParams(side_offset_mm=side_offset_mm, offset_jitter_mm=0.3)
    tactile = ScriptedTactileSensor(
        ScriptedTactileConfig(
            script=GraspScript(grasps=[grasp], loop=False, start_delay_s=0.3), generator=generator
        )
    )
    arm = SimulatedArm()
    arm.connect()
    pose = arm.tcp_pose()
    lo, hi = pose[:3] - 0.05, pose[:3] + 0.05
    if box_face_mm is not None:  # the face the pattern's shift points at, this close
        angle_class, _ = classes_of(pattern)
        dx, dz = offset_direction(angle_class)
        toward = rotvec_to_matrix(pose[3:]) @ np.array([dx, 0.0, dz])  # class 1: +offset
        axis = int(np.argmax(np.abs(toward)))
        if toward[axis] > 0:
            hi[axis] = pose[axis] + box_face_mm / 1000
        else:
            lo[axis] = pose[axis] - box_face_mm / 1000
    arm.limits.workspace_min, arm.limits.workspace_max = tuple(lo), tuple(hi)
    robot = RobotNode(rc, tactile, arm=arm, recorder=ListRecorder())
    operators = {}
    for name in ("a", "b"):
        oc = OperatorConfig()
        oc.link.telemetry_endpoint, oc.link.command_endpoint = tel, cmd
        oc.link.signing_key_file = secrets[name]
        oc.link.request_control = name == "a"
        operators[name] = OperatorNode(oc, InMemoryServoBus())
    stop = threading.Event()
    threads = [threading.Thread(target=robot.run, args=(stop,), daemon=True)]
    threads += [
        threading.Thread(target=o.run, args=(stop,), daemon=True) for o in operators.values()
    ]
    for t in threads:
        t.start()
    return robot, arm, operators, stop, threads, (lo, hi)


@pytest.fixture
def make_cell(tmp_path, quiet_gc):
    made = []

    def make(pattern: int, box_face_mm: float | None = None, side_offset_mm: float | None = None):
        cell = _cell(tmp_path, pattern, box_face_mm, side_offset_mm)
        made.append(cell)
        robot, _arm, ops, *_ = cell
        wait(lambda: ops["a"].holds_lease, 30, "a's lease")
        wait(lambda: robot.last_stimulus is not None and robot.last_stimulus.contact, 10,
             "the scripted grasp")  # fmt: skip
        time.sleep(0.5)  # both operators' clocks known at the robot
        return cell

    yield make
    for _robot, arm, _ops, stop, threads, _box in made:
        stop.set()
        for t in threads:
            t.join(timeout=10)
        arm.disconnect()


def test_the_assist_never_leaves_the_box_however_its_pattern_pushes(make_cell):
    """A pattern whose re-grasps push toward a face 3 mm away: the TCP stops at the face."""
    robot, arm, ops, _stop, _threads, (lo, hi) = make_cell(SHIFT_ONLY, box_face_mm=3.0)
    start = arm.sim.tcp_pose()[:3]
    a = ops["a"]
    worst = 0.0  # metres beyond the box, as the simulator has the TCP
    with holding(a):
        end = time.monotonic() + 20
        while phase(a) != PHASE_CODES["gave_up"] and time.monotonic() < end:
            xyz = arm.sim.tcp_pose()[:3]
            worst = max(worst, float(np.max(np.maximum(lo - xyz, xyz - hi))))
            time.sleep(0.005)
        stats = a.snapshot().robot_stats
    moved = float(np.linalg.norm(arm.sim.tcp_pose()[:3] - start))
    assert stats.get("assist_phase") == PHASE_CODES["gave_up"], stats
    assert stats["assist_regrasps"] == robot.config.assist.max_regrasps
    assert moved > 0.0025, f"the assist moved the TCP only {moved * 1000:.2f} mm toward the face"
    assert worst <= 0.0001, f"the TCP went {worst * 1000:.2f} mm beyond the workspace box"
    # every step is in the recording: its phases, and each command with what the arm was sent
    records = robot.recorder.channel("robot/assist")
    phases = [r["phase"] for r in records]
    assert phases[:4] == ["waiting", "release", "shift", "turn"], records
    assert phases.count("release") == robot.config.assist.max_regrasps and "gave_up" in phases
    jogs = [
        r for r in robot.recorder.channel("robot/command")
        if r.get("by") == "assist" and r["action"] == "arm_jog" and r["outcome"] == "applied"
    ]  # fmt: skip
    assert len(jogs) >= 10, "the assist's jogs are recorded"
    cap = robot.config.assist.shift_speed_m_s + 1e-9
    assert all(np.linalg.norm(r["sent_velocity"][:3]) <= cap for r in jogs)


def test_one_shift_puts_the_pad_centre_on_the_bands_measured_axis(make_cell):
    """A pipette met 8 mm off centre: the shift is the band's offset, not a fixed step.

    A fixed 5 mm step left it 3 mm off, still "left": a second re-grasp, about
    1.5 s more, on every pipette a tilt put far from its hole's line.
    """
    robot, arm, ops, *_ = make_cell(SHIFT_ONLY, side_offset_mm=8.0)
    a = ops["a"]
    start = arm.sim.tcp_pose()
    with holding(a):
        wait(
            lambda: any(r["phase"] == "turn" for r in robot.recorder.channel("robot/assist")),
            10,
            "the first shift to end",
        )
        moved = arm.sim.tcp_pose()[:3] - start[:3]
    band = measure_band(robot.pipeline.last_frame)  # the grasp is held still: what it saw
    assert band is not None
    ox, oz = band.offset_mm
    assert np.hypot(ox, oz) > 7.0, band  # the scripted grasp: 8 mm off, give or take 0.3
    in_tool = rotvec_to_matrix(start[3:]).T @ moved * 1000  # mm, tool frame
    np.testing.assert_allclose(in_tool, (ox, 0.0, oz), atol=0.6)


def test_a_stop_ends_the_assist_within_the_arms_stop_budget_and_a_non_holder_is_refused(
    make_cell,
):
    robot, arm, ops, *_ = make_cell(SHIFT_AND_TURN)
    a, b = ops["a"], ops["b"]
    with holding(b):  # b holds no lease: refused as its jog would be
        time.sleep(1.0)
        assert not moving(arm), "a non-holder's assist moved the arm"
        assert robot.stats()["commands_not_controller"] >= 5
        assert phase(a) == PHASE_CODES["off"]
    with holding(a):
        wait(lambda: moving(arm), 10, "the assist to move the arm")
        wait(lambda: phase(a) == PHASE_CODES["turn"], 10, "the assist to turn the wrist")
        t_stop = time.monotonic()
        b.send_command("arm_stop")  # anyone's STOP
        wait(lambda: still(arm), 5, "the arm to stop")
        took = time.monotonic() - t_stop
        assert took <= ARM_STILL_BUDGET_S, (
            f"the arm still {took * 1000:.0f} ms after the stop (budget "
            f"{ARM_STILL_BUDGET_S * 1000:.0f} ms; a loaded machine adds its own delay)"
        )
        end = time.monotonic() + 1.0
        while time.monotonic() < end:  # a holds on: nothing moves
            assert not moving(arm), "the arm moved again under a held assist after a stop"
            time.sleep(0.01)
        # ended, then off: the latch refuses a's enables as it would a's jogs
        assert phase(a) in (PHASE_CODES["ended"], PHASE_CODES["off"])
        assert robot.stats()["commands_stop_latched"] >= 5
        assert robot.assist.why == "arm_stop from b"


def test_letting_go_of_the_enable_stops_the_assist_as_a_jog_deadman(make_cell):
    _robot, arm, ops, *_ = make_cell(SHIFT_AND_TURN)
    a = ops["a"]
    with holding(a) as sent:
        wait(lambda: phase(a) == PHASE_CODES["turn"], 10, "the assist to turn the wrist")
        wait(lambda: moving(arm), 5, "the turn to move the wrist")
    last = sent[-1]
    wait(lambda: still(arm), 5, "the arm to stop after the enable was let go")
    took = time.monotonic() - last
    budget = arm.limits.jog_timeout_s + ARM_STILL_BUDGET_S
    assert took <= budget, f"still {took * 1000:.0f} ms after the last enable (budget {budget})"
    wait(lambda: phase(a) == PHASE_CODES["off"], 3, "the heartbeat to say off")
    time.sleep(0.5)
    assert still(arm), "the arm moved again after the enable was let go"


def test_a_lease_hand_over_ends_the_assist_and_stills_the_arm(make_cell):
    robot, arm, ops, *_ = make_cell(SHIFT_AND_TURN)
    a, b = ops["a"], ops["b"]
    b.send_command("lease_request")
    wait(lambda: b.lease_pending is not None, 3, "b's request")
    with holding(a):
        wait(lambda: phase(a) == PHASE_CODES["turn"], 10, "the assist to turn the wrist")
        wait(lambda: moving(arm), 5, "the turn to move the wrist")
        t_grant = time.monotonic()
        a.send_command("lease_grant", grantee=b.signer.public)
        wait(lambda: still(arm), 5, "the arm to stop at the hand-over")
        took = time.monotonic() - t_grant
        assert took <= ARM_STILL_BUDGET_S, f"still {took * 1000:.0f} ms after the hand-over"
        end = time.monotonic() + 1.0
        while time.monotonic() < end:  # a still holds the assist: refused, as its jogs would be
            assert not moving(arm), "a's assist moved the arm after a handed the lease over"
            time.sleep(0.01)
        assert b.holds_lease
    assert robot.assist.why.startswith("control lease now"), robot.assist.why
