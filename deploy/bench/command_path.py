"""The robot's command path: what a command costs, and the frame loop while commands flood in.

``RobotUnderCommands`` is the rig both this bench section and the system
tests use: the robot node as its own process (as deployed) with its real
ur-rtde and Robotiq socket drivers against the UR and gripper simulators,
which this process serves, and a passive listener on the robot's telemetry.
Everything is observed from outside: the stimuli on the wire, the arm's
motion in the UR simulator, the robot's counters in its heartbeats.
"""

from __future__ import annotations

import multiprocessing
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import zmq

from common.clock import now_ns
from common.errors import DeviceError
from common.messages import Heartbeat, Stimulus
from common.transport import Subscriber, free_loopback_ports
from deploy.unit_policy import set_niceness, unit_nice

PUBLISH_HZ = 60.0
FLOOD_VELOCITY = [0.05, 0.0, 0.0, 0.0, 0.0, 0.0]

_ROBOT_TOML = """
[robot]
publish_rate_hz = {rate}
[robot.render]
mode = "mask_ground_truth"
deadband_n = 0.0  # every rendered frame that differs is sent: a steady stream to watch
[robot.tactile]
kind = "scripted"
[robot.tactile.script]
loop = false
grasps = [{{pattern = 6, grip_level = 25, ramp_s = 0.1, hold_s = 3600.0}}]
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


class Telemetry:
    """Every message the robot publishes, with its local receive time, from a passive listener."""

    def __init__(self, endpoint: str) -> None:
        self.ctx = zmq.Context()
        self.sub = Subscriber(self.ctx, endpoint, bind=False)
        self.messages: list[tuple[int, Any]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="telemetry", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            if self.sub.poll(0.01):
                self.messages.extend((t, m) for m, t in self.sub.drain())

    def times(self, kind: type, t0: int = 0, t1: int = 2**63) -> list[int]:
        return [t for t, m in self.messages if isinstance(m, kind) and t0 <= t <= t1]

    def sent_times(self, kind: type, t0: int = 0, t1: int = 2**63) -> list[int]:
        """The robot's own send stamps (same machine, same clock) of what arrived in [t0, t1].

        Gaps here are the robot's; gaps in :meth:`times` also hold this listener's own stalls.
        """
        return [m.t_send_ns for t, m in self.messages if isinstance(m, kind) and t0 <= t <= t1]

    def robot_stats(self) -> dict[str, float]:
        beats = [m for _, m in self.messages if isinstance(m, Heartbeat)]
        return beats[-1].stats if beats else {}

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        self.sub.close()
        self.ctx.term()


class ArmWatch:
    """Samples the simulated controller's TCP speed (not the node's view of it) at ~100 Hz.

    ``sim`` may be replaced by a new simulator (the controller restarted); while
    none answers there are no samples, never a made-up still arm.
    """

    def __init__(self, sim: Any) -> None:
        self.sim = sim
        self.samples: list[tuple[int, float]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="arm-watch", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.01):
            try:
                speed = float(np.linalg.norm(self.sim.tcp_speed()))
            except (DeviceError, OSError, ValueError):  # the controller is gone: a gap
                continue
            self.samples.append((now_ns(), speed))

    def moving_between(self, t0: int, t1: int, above: float = 1e-4) -> list[int]:
        """Sample times in [t0, t1] at which the TCP moved faster than ``above`` m/s."""
        return [t for t, v in self.samples if t0 <= t <= t1 and v > above]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)


class RobotUnderCommands:
    """The robot node process on its simulators, watched from outside (a context manager)."""

    def __init__(self, workdir: Path | None = None) -> None:
        self.workdir = Path(workdir or tempfile.mkdtemp(prefix="deepxpalm-cmd-"))
        self.telemetry_endpoint, self.command_endpoint = (
            f"tcp://127.0.0.1:{p}" for p in free_loopback_ports(2)
        )

    def __enter__(self) -> RobotUnderCommands:
        from robot_side.arm.sim import URSimProcess
        from robot_side.gripper.sim import GripperSimConfig, GripperSimServer

        self.arm_sim = URSimProcess().start()
        self.gripper_sim = GripperSimServer(GripperSimConfig(port=0)).start()
        config = self.workdir / "robot.toml"
        config.write_text(
            _ROBOT_TOML.format(
                rate=PUBLISH_HZ,
                gripper_port=self.gripper_sim.port,
                arm_host=self.arm_sim.host,
                tel=self.telemetry_endpoint,
                cmd=self.command_endpoint,
            )
        )
        self.config = config
        self.log = self.workdir / "robot.log"
        self.telemetry = Telemetry(self.telemetry_endpoint)
        self.arm = ArmWatch(self.arm_sim)
        try:
            self.start_node()
        except RuntimeError:
            self.__exit__()
            raise
        time.sleep(0.3)
        return self

    def start_node(self, timeout_s: float = 60.0) -> None:
        """Start the robot node process; returns once it publishes (again, after a restart)."""
        t0 = now_ns()
        nice = unit_nice("robot")
        with self.log.open("a") as out:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "deploy.cli", "-v", "robot", "--config", str(self.config)],
                stdout=out,
                stderr=subprocess.STDOUT,
                preexec_fn=lambda: set_niceness(nice),  # as its unit runs it
            )
        deadline = time.monotonic() + timeout_s
        while not self.telemetry.times(Stimulus, t0):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"the robot node never published:\n{self.log.read_text()}")
            time.sleep(0.02)

    def log_with_stacks(self) -> str:
        """The node's log, ending with every thread's stack (``kill -USR1``) if it still runs."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGUSR1)
            time.sleep(0.5)
        return self.log.read_text()

    def __exit__(self, *exc: object) -> None:
        self.arm.close()
        self.telemetry.close()
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.gripper_sim.stop()
        self.arm_sim.stop()

    def arm_controller_gone(self, kill: bool) -> str:
        """The UR controller vanishes: ``kill -9`` of its process, or its servers closed cleanly.

        Returns its address, where :meth:`arm_controller_back` starts it again.
        """
        host = self.arm_sim.host
        if kill:
            self.arm_sim.kill()
        else:
            self.arm_sim.stop()
        return host

    def arm_controller_back(self, host: str) -> None:
        """A fresh controller on the same address (rebooted, or its cable plugged back)."""
        from robot_side.arm.sim import URSimConfig, URSimProcess

        self.arm_sim = URSimProcess(URSimConfig(host=host)).start()
        self.arm.sim = self.arm_sim

    def stimulus_rate(self, t0: int, t1: int) -> float:
        return len(self.telemetry.times(Stimulus, t0, t1)) / ((t1 - t0) / 1e9)

    def flood(self, n: int) -> dict[str, int]:
        """``n`` valid jogs from a client process of its own; its first and last send times."""
        from deploy.bench.command_flood import run

        mp = multiprocessing.get_context("spawn")
        parent, child = mp.Pipe(duplex=False)
        args = (self.telemetry_endpoint, self.command_endpoint, n, FLOOD_VELOCITY, child)
        proc = mp.Process(target=run, args=args, daemon=True)
        t_start = now_ns()
        proc.start()
        if not parent.poll(300):
            proc.kill()
            raise RuntimeError("the flood client never finished")
        report = parent.recv()
        proc.join(10)
        return {"t_start_ns": t_start, **report}


def command_cost(n: int) -> dict[str, Any]:
    """Microseconds per command through the robot's intake: read, decode and admission."""
    from common.clock_sync import ClockSync
    from common.messages import Command
    from common.transport import Publisher
    from robot_side.command_gate import CommandGate

    ctx = zmq.Context()
    sub = Subscriber(ctx, "tcp://127.0.0.1:*", bind=True, rcvhwm=0)
    pub = Publisher(ctx, sub.endpoint, bind=False, sndhwm=0)
    clock = ClockSync()
    clock.add_sample(0, 0, 0, 0)
    gate = CommandGate(clock, 250_000_000)
    velocity = tuple(FLOOD_VELOCITY)
    try:
        deadline = time.monotonic() + 5
        while not sub.poll(0.01):  # until connected
            pub.send(Command(seq=1, t_send_ns=now_ns(), action="arm_stop"))
            if time.monotonic() > deadline:
                raise RuntimeError("loopback PUB/SUB never connected")
        sub.drain()
        per_batch: list[float] = []
        for i in range(n):
            pub.send(
                Command(
                    seq=i + 2, t_send_ns=now_ns(), action="arm_jog", velocity=velocity, session=1
                )
            )
        time.sleep(0.5)
        read = 0
        while read < n:
            t = time.perf_counter_ns()
            batch = sub.drain(32)
            now = now_ns()
            for msg, t_recv in batch:
                gate.admit(msg, t_recv, now)
            if not batch:
                break
            per_batch.append((time.perf_counter_ns() - t) / len(batch) / 1e3)
            read += len(batch)
    finally:
        pub.close()
        sub.close()
        ctx.term()
    arr = np.array(per_batch)
    return {
        "messages": read,
        "median_us": float(np.median(arr)),
        "p99_us": float(np.percentile(arr, 99)),
    }


def measure(n_flood: int, baseline_s: float, n_cost: int) -> dict[str, Any]:
    """The section: command cost, then the frame loop and the arm under a flood."""
    from deploy.bench.timing import machine_load

    out: dict[str, Any] = {
        "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
        "load_before": machine_load(),
        "cost": command_cost(n_cost),
        "flood_messages": n_flood,
    }
    with RobotUnderCommands() as rig:
        t0 = now_ns()
        time.sleep(baseline_s)
        t1 = now_ns()
        base_times = sorted(rig.telemetry.sent_times(Stimulus, t0, t1))
        report = rig.flood(n_flood)
        time.sleep(2.5)  # the backlog in the kernel's and ZeroMQ's queues ages out
        first, last = report["t_first_ns"], report["t_last_ns"]
        window_end = last + 2_000_000_000
        during_times = sorted(rig.telemetry.sent_times(Stimulus, first, window_end))
        moving = rig.arm.moving_between(last, now_ns())
        stats = rig.telemetry.robot_stats()
    base_gaps = np.diff(base_times) / 1e6
    gaps = np.diff(during_times) / 1e6
    normal = len(base_times) / ((t1 - t0) / 1e9)
    during = len(during_times) / ((window_end - first) / 1e9)
    out.update(
        flood_s=(last - first) / 1e9,
        stimuli_per_s_normal=normal,
        stimuli_per_s_during=during,
        rate_ratio=during / normal if normal else 0.0,
        interval_ms_normal={"median": float(np.median(base_gaps)), "max": float(base_gaps.max())},
        interval_ms_during={
            "median": float(np.median(gaps)),
            "p99": float(np.percentile(gaps, 99)),
            "max": float(gaps.max()),
        },
        arm_moving_ms_after_last_send=(moving[-1] - last) / 1e6 if moving else 0.0,
        load_after=machine_load(),
        robot_counters={
            k: stats.get(k, 0.0)
            for k in (
                "commands_received",
                "commands_stale",
                "commands_superseded",
                "commands_applied",
                "command_backlog_pauses",
                "deadman_trips",
            )
        },
    )
    return out
