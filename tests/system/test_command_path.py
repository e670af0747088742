"""The robot's command path under load, seen from outside: the wire, the arm and gripper simulators.

The robot node runs as its own process, as deployed, with its real UR driver
(ur-rtde) against the UR simulator and its real Robotiq socket driver
against the gripper simulator, both served from this test; the operators
here are raw clients written from docs/protocol.md.
"""

from __future__ import annotations

import multiprocessing
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from flood_client import run as flood
from tests_support import ProtocolOperator, free_ports

from common.clock import now_ns
from common.codec import encode
from common.messages import Heartbeat, Stimulus
from common.transport import Publisher, Subscriber
from robot_side.arm.sim import URSimProcess
from robot_side.gripper.base import GripLevels
from robot_side.gripper.sim import GripperSimConfig, GripperSimServer

N_FLOOD = 100_000
PUBLISH_HZ = 60.0


class ArmWatch:
    """Samples the simulated controller's TCP speed (not the node's view of it) at ~100 Hz."""

    def __init__(self, sim: URSimProcess) -> None:
        self.sim = sim
        self.samples: list[tuple[int, float]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.01):
            speed = float(np.linalg.norm(self.sim.tcp_speed()))
            self.samples.append((now_ns(), speed))

    def moving_between(self, t0: int, t1: int, above: float = 1e-4) -> list[int]:
        return [t for t, v in self.samples if t0 <= t <= t1 and v > above]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)


class Telemetry:
    """Every message the robot publishes, with its local receive time, from a passive listener."""

    def __init__(self, ctx_endpoint: str) -> None:
        import zmq

        self.ctx = zmq.Context()
        self.sub = Subscriber(self.ctx, ctx_endpoint, bind=False)
        self.messages: list[tuple[int, object]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            if self.sub.poll(0.01):
                self.messages.extend((t, m) for m, t in self.sub.drain())

    def times(self, kind: type, t0: int = 0, t1: int = 2**63) -> list[int]:
        return [t for t, m in self.messages if isinstance(m, kind) and t0 <= t <= t1]

    def robot_stats(self) -> dict[str, float]:
        beats = [m for _, m in self.messages if isinstance(m, Heartbeat)]
        return beats[-1].stats if beats else {}

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        self.sub.close()
        self.ctx.term()


ROBOT_TOML = """
[robot]
publish_rate_hz = {rate}
[robot.render]
mode = "mask_ground_truth"
deadband_n = 0.0  # every rendered frame that differs is sent: a steady stream to watch
[robot.tactile]
kind = "scripted"
[robot.tactile.script]
loop = false
grasps = [{{pattern = 6, grip_level = 25, ramp_s = 0.1, hold_s = 600.0}}]
[robot.gripper]
kind = "robotiq_socket"
host = "127.0.0.1"
port = {gripper_port}
[robot.arm]
kind = "ur_rtde"
host = "{arm_host}"
[robot.link]
telemetry_endpoint = "{tel}"
command_endpoint = "{cmd}"
"""


@pytest.fixture
def cell(tmp_path: Path):
    """The robot node as its own process (as deployed), its devices' simulators in this one."""
    tel, cmd = (f"tcp://127.0.0.1:{p}" for p in free_ports(2))
    with URSimProcess() as arm_sim, GripperSimServer(GripperSimConfig(port=0)) as gripper_sim:
        config = tmp_path / "robot.toml"
        config.write_text(
            ROBOT_TOML.format(
                rate=PUBLISH_HZ,
                gripper_port=gripper_sim.port,
                arm_host=arm_sim.host,
                tel=tel,
                cmd=cmd,
            )
        )
        log = tmp_path / "robot.log"
        with log.open("w") as out:
            proc = subprocess.Popen(
                [sys.executable, "-m", "deploy.cli", "robot", "--config", str(config)],
                stdout=out,
                stderr=subprocess.STDOUT,
            )
        telemetry = Telemetry(tel)
        watch = ArmWatch(arm_sim)
        try:
            deadline = time.monotonic() + 60
            while not telemetry.times(Stimulus) and time.monotonic() < deadline:
                assert proc.poll() is None, log.read_text()[-3000:]
                time.sleep(0.05)
            assert telemetry.times(Stimulus), "the robot node never published"
            time.sleep(0.3)
            yield arm_sim, gripper_sim, telemetry, watch, (tel, cmd)
        finally:
            watch.close()
            telemetry.close()
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(15)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def _rate(times: list[int], t0: int, t1: int) -> float:
    return len([t for t in times if t0 <= t <= t1]) / ((t1 - t0) / 1e9)


def test_a_flood_of_jogs_neither_starves_the_palm_nor_outlives_the_sender(cell):
    _, _, telemetry, watch, (tel, cmd) = cell
    t0 = now_ns()
    time.sleep(2.0)
    normal = _rate(telemetry.times(Stimulus), t0, now_ns())
    assert normal > 0.8 * PUBLISH_HZ, f"the scripted grasp gave only {normal:.0f} stimuli/s"

    mp = multiprocessing.get_context("spawn")
    parent, child = mp.Pipe(duplex=False)
    velocity = [0.05, 0.0, 0.0, 0.0, 0.0, 0.0]
    t_start = now_ns()
    proc = mp.Process(target=flood, args=(tel, cmd, N_FLOOD, velocity, child), daemon=True)
    proc.start()
    assert parent.poll(120), "the flood client never finished"
    report = parent.recv()
    proc.join(10)
    t_first, t_last = report["t_first_ns"], report["t_last_ns"]
    time.sleep(2.5)  # let the backlog in the kernel's and ZeroMQ's queues age out

    # the operator's jog moved the arm before the flood: the test can see motion at all
    assert watch.moving_between(t_start, t_first, above=0.01), "the pre-flood jog never moved"
    # the arm is still 400 ms after the sender's last send, and stays still
    late = watch.moving_between(t_last + 400_000_000, now_ns())
    assert not late, f"the arm moved {(late[-1] - t_last) / 1e6:.0f} ms after the last send"
    # the palm kept its stimuli while the flood and its backlog were read
    during = _rate(telemetry.times(Stimulus), t_first, t_last + 2_000_000_000)
    assert during >= 0.9 * normal, f"stimuli at {during / normal:.2f} of normal during the flood"
    stats = telemetry.robot_stats()
    assert stats.get("commands_stale", 0) + stats.get("commands_superseded", 0) > 0
    print(
        f"\nflood: {N_FLOOD} jogs in {(t_last - t_first) / 1e9:.2f} s; stimuli {during:.1f}/s "
        f"against {normal:.1f}/s; received {stats.get('commands_received', 0):.0f}, "
        f"stale {stats.get('commands_stale', 0):.0f}, superseded "
        f"{stats.get('commands_superseded', 0):.0f}, backlog pauses "
        f"{stats.get('command_backlog_pauses', 0):.0f}"
    )


def test_jog_and_stop_repeated_never_stall_the_telemetry(cell):
    _, _, telemetry, watch, (tel, cmd) = cell
    import zmq

    ctx = zmq.Context()
    op = ProtocolOperator(
        Subscriber(ctx, tel, bind=False), Publisher(ctx, cmd, bind=False), session=11
    )
    try:
        op.sync()
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
    stim = telemetry.times(Stimulus, t0, t1)
    beats = telemetry.times(Heartbeat, t0, t1)
    stim_gap = max(np.diff(stim)) / 1e6
    beat_gap = max(np.diff(beats)) / 1e6
    assert watch.moving_between(t0, t1, above=0.01), "the jogs never moved the arm"
    assert stim_gap <= 2 * 1000 / PUBLISH_HZ, f"a {stim_gap:.1f} ms gap in the stimuli"
    assert beat_gap <= 70, f"a {beat_gap:.1f} ms gap between heartbeats"
    assert telemetry.robot_stats().get("deadman_trips", 0) == 0
    print(f"\n{cycles} jog+stop cycles: stimulus gap {stim_gap:.1f} ms, heartbeat {beat_gap:.1f}")


def test_a_replayed_command_is_refused_and_counted(cell):
    _, gripper_sim, telemetry, _, (tel, cmd) = cell
    import zmq

    ctx = zmq.Context()
    op = ProtocolOperator(
        Subscriber(ctx, tel, bind=False), Publisher(ctx, cmd, bind=False), session=21
    )
    replayer = Publisher(ctx, cmd, bind=False)  # a connection of its own
    model = gripper_sim.model

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
