"""On a 100 ms link no exported jog row outlives the arm's motion.

In both tests the arm is the real safety layer (``MemoryArm``: the jog
deadman thread and its stop, which it timestamps), and a jog row is late
when the arm's deadman had stopped it before the row's time. The first runs
the whole chain: robot node (recording), the link simulator with 100 ms
each way, operator node jogging in bursts. The second writes the recording
itself, jogging the arm as the node does (each jog 100 ms after its send
time, ``robot/command`` written after the jog returned), so it runs in
seconds and does not depend on the link's timing.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pyarrow.parquet as pq
from synthetic import MS, POSE, robot_recording
from tests_support import free_ports

from common.clocks.clock import now_ns
from common.netsim.proxy import Endpoints, LinkSimulator
from common.netsim.scenario import scenario_from_dict
from common.recording.mcap_recorder import node_recorder, read_recording
from deploy.export.cli import export
from deploy.export.resample import ExportConfig
from operator_side.node import OperatorNode
from operator_side.node.config import OperatorConfig
from operator_side.servos.in_memory import InMemoryServoBus
from robot_side.arm.memory import MemoryArm, MemoryArmConfig
from robot_side.node import RobotNode
from robot_side.node.config import RobotConfig
from robot_side.tactile.script import GraspScript, GraspStep
from robot_side.tactile.scripted import ScriptedTactileConfig, ScriptedTactileSensor

LINK_MS = 100
FPS = 100
JOG = (0.02, 0.0, 0.0, 0.0, 0.0, 0.0)


def _late_jog_rows(path, out, arm) -> tuple[list[float], int]:
    """Export ``path``; (how long after the arm's deadman stop each late jog row is, jog rows)."""
    export([path], out, ExportConfig(fps=FPS, episodes="session"))
    ep = pq.read_table(out / "meta/episodes/chunk-000/file-000.parquet").to_pylist()[0]
    rows = pq.read_table(out / "data/chunk-000/file-000.parquet").to_pydict()
    t_rows = ep["deepxpalm/t_first_ns"] + np.round(np.arange(ep["length"]) * 1e9 / FPS)
    jogging = np.array([any(a[:6]) for a in rows["action"]])
    jogs = np.array(arm.jog_times_ns)
    stops = np.array(arm.stop_times_ns)
    late = []
    for t in t_rows[jogging]:
        last_jog = jogs[jogs <= t].max()
        stopped = stops[(stops > last_jog) & (stops <= t)]
        if stopped.size:
            late.append((t - stopped[0]) / 1e6)
    return late, int(jogging.sum())


def test_through_the_link_simulator_no_jog_row_outlives_the_arm(tmp_path):
    tel, cmd = (f"tcp://127.0.0.1:{p}" for p in free_ports(2))
    rc = RobotConfig()
    rc.render.mode = "mask_ground_truth"
    rc.link.telemetry_endpoint, rc.link.command_endpoint = tel, cmd
    hold = GraspScript(grasps=[GraspStep(pattern=6, grip_level=25, ramp_s=0.1, hold_s=60.0)])
    arm = MemoryArm()
    arm.connect()
    path = tmp_path / "robot.mcap"
    recorder = node_recorder(path, rc, "robot")
    sensor = ScriptedTactileSensor(ScriptedTactileConfig(script=hold))
    robot = RobotNode(rc, sensor, arm=arm, recorder=recorder)
    stop = threading.Event()
    threads = [threading.Thread(target=robot.run, args=(stop,), daemon=True)]
    threads[0].start()
    delay = {"delivery": "datagram", "delay_ms": LINK_MS}
    sim = LinkSimulator(
        scenario_from_dict({"name": "100 ms", "both": delay}),
        endpoints=Endpoints(
            robot_telemetry=tel,
            robot_commands=cmd,
            operator_telemetry="tcp://127.0.0.1:*",
            operator_commands="tcp://127.0.0.1:*",
        ),
    )
    sim.start()
    oc = OperatorConfig()
    oc.link.telemetry_endpoint = sim.operator_telemetry_endpoint
    oc.link.command_endpoint = sim.operator_commands_endpoint
    operator = OperatorNode(oc, InMemoryServoBus())
    threads.append(threading.Thread(target=operator.run, args=(stop,), daemon=True))
    threads[1].start()
    try:
        deadline = time.monotonic() + 20
        while robot.clock.offset_ns is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert robot.clock.offset_ns is not None, "the robot never learnt the operator's clock"
        for _burst in range(4):  # a jog key held 0.5 s, then let go for 0.6 s
            end = time.monotonic() + 0.5
            while time.monotonic() < end:
                operator.send_command("arm_jog", velocity=JOG)
                time.sleep(0.033)
            time.sleep(0.6)
    finally:
        stop.set()
        for t in threads:
            t.join(timeout=5)
        sim.stop()
        recorder.close()
        arm.disconnect()
    applied = [
        r
        for ch, _, r in read_recording(path)
        if ch == "robot/command" and r["action"] == "arm_jog" and r["outcome"] == "applied"
    ]
    assert len(applied) > 20, "too few jogs reached the arm to judge"
    assert all(r["t_sent_ns"] is not None and r["sent_velocity"] for r in applied)
    late, jog_rows = _late_jog_rows(path, tmp_path / "ds", arm)
    assert jog_rows > 0.3 * 4 * 0.5 * FPS
    assert not late, (
        f"{len(late)} of {jog_rows} jog rows come after the arm's deadman had stopped it, "
        f"up to {max(late):.0f} ms after"
    )


def test_with_explicit_send_and_record_times_no_jog_row_outlives_the_arm(tmp_path):
    arm = MemoryArm(MemoryArmConfig(start_pose=tuple(POSE)))
    arm.connect()
    velocity = list(JOG)
    commands = []  # (record time, send time, velocity sent): the node's robot/command records
    try:
        for _burst in range(3):  # the operator holds a jog key 0.4 s, then lets go for 0.6 s
            end = time.monotonic() + 0.4
            while time.monotonic() < end:
                sent_ns = now_ns() - LINK_MS * MS
                sent = arm.jog(velocity, sent_ns / 1e9)
                commands.append((now_ns(), sent_ns, sent))
                time.sleep(0.033)
            time.sleep(0.6)
    finally:
        arm.disconnect()
    t0 = commands[0][0] - 500 * MS
    t_end = commands[-1][0] + 800 * MS
    pending = list(commands)

    def add_commands(rec, t):
        while pending and pending[0][0] <= t:
            t_rec, t_sent, sent = pending.pop(0)
            rec.write(
                "robot/command",
                t_rec,
                {
                    "seq": 1,
                    "action": "arm_jog",
                    "grip_level": None,
                    "velocity": velocity,
                    "sent_velocity": [float(v) for v in sent],
                    "t_sent_ns": t_sent,
                    "outcome": "applied",
                },
            )

    path = tmp_path / "robot.mcap"
    robot_recording(path, (t_end - t0) / 1e9, t0_ns=t0, extra=add_commands)
    late, jog_rows = _late_jog_rows(path, tmp_path / "ds", arm)
    assert jog_rows > 0.3 * 3 * 0.4 * FPS  # most of the time the key was held
    assert not late, (
        f"{len(late)} of {jog_rows} jog rows come after the arm's deadman had stopped it, "
        f"up to {max(late):.0f} ms after"
    )
