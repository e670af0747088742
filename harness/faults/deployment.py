"""Every process of a deployment on this machine, each started as on its own machine.

The fabric's router, the robot node, the operator node, the recorder and the
video server run as ``harness.fleet`` starts them (QUIC with the members'
certificates, a roster, signed commands); the robot and the recorder connect
to the router directly, the operator through ``deepxpalm netsim`` in datagram
mode (its QUIC connection's UDP crosses the link, as over a real network);
every device is a simulator in a process of its own (``deepxpalm sim
ur|gripper|tactile|servos``) so that killing a node never kills its device. The demo's supervisor
(``deploy.supervisor``) plays systemd on a thread of its own:
a process of a shipped unit that ends is started again after the unit's
RestartSec= when its Restart= says so, runs its ExecStopPost= after any end
(the operator's lifts the palm), and ends a process whose WatchdogSec= passed
without a ping (``deploy.watchdog.UnitWatchdog``).
"""

from __future__ import annotations

import contextlib
import json
import logging
import signal
import subprocess
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from common.transport import free_loopback_ports
from deploy.demo import spawn_cli
from deploy.supervisor import Child, StopPost, Supervisor, stop_post_args
from deploy.unit_policy import RestartPolicy, policy
from deploy.watchdog import UnitWatchdog
from harness.fleet import Fleet, Proc
from harness.processes import stop
from operator_side.servos.sts_sim import simulated_driver_settings

log = logging.getLogger(__name__)

ROBOT, OPERATOR, RECORDER = "cell", "op", "rec"

#: the grasp the tactile board feels for the whole run, and the renderer that needs no model
_BOARD_TOML = """
seed = 7
zero_counts_min = 300.0
zero_counts_max = 300.0
gain_spread = 0.0
counts_at_9n = 3000.0
link_dir = "{link_dir}"
[script]
loop = false
start_delay_s = 0.5
grasps = [{{pattern = 6, grip_level = 25, ramp_s = 0.1, hold_s = 3600.0}}]
"""

_ROBOT_DEVICES = """
[robot.render]
mode = "direct"
[robot.tactile]
kind = "serial"
port = "{tactile_port}"
zero_counts = 300.0
gain_n_per_count = 0.003
auto_reconnect = true
[robot.gripper]
kind = "robotiq_socket"
host = "{gripper_host}"
port = {gripper_port}
"""

#: a pipette the fingers stop on at every grip level (the default gives way past level 20's goal)
_PIPETTE = """[model]
compression_at_full_force = 20.0
"""

#: the operator's bus: the simulator's pty, with the driver settings a simulated bus needs
_SERVOS = """kind = "feetech"
port = "{port}"
retries = {retries}
reply_timeout_ms = {reply_timeout_ms}
"""

#: the link: a wired LAN carrying the operator's QUIC datagrams (the fabric), and an outage of
#: ``outage_s`` from ``outage_at_s`` after netsim starts: every datagram of it lost, both ways
_SCENARIO_TOML = """
name = "lan-with-outage"
description = "wired LAN with one scheduled outage (the fault matrix)"
[both]
delivery = "datagram"
delay_ms = 0.1
jitter_ms = 0.02
distribution = "normal"
outages = [[{t1}, {t2}]]
"""

#: hardware and the network come back by themselves: a device's power, the link. The
#: supervisor (a thread that lives as long as the deployment) starts them again, because a
#: child's PR_SET_PDEATHSIG follows the *thread* that forked it: one forked from a short
#: thread would be sent its death signal the moment that thread ends
DEVICE_BACK = RestartPolicy(unit="", restart="on-failure", restart_sec=2.0, watchdog_sec=0.0)
DEVICES = ("ur", "gripper", "tactile", "servos", "netsim")

#: never, for a deployment whose link does not fail
NO_OUTAGE_AT_S = 1e6


class LateWakes:
    """When the operator's loop woke over 100 ms late, from its status file (``--status-file``,
    rewritten every 0.1 s): its counters ``late_wakes`` and ``late_wake_ms`` (their sum), read
    on each poll of the supervisor. A starved operator cannot lift the palm meanwhile.

    ``wakes``: (due, woke) on the monotonic clock (s), the wake known to the status file's
    period: it woke by the status that first counted it; several counted by one status are
    one wake as late as their sum."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.wakes: list[tuple[float, float]] = []
        self._mtime_ns = 0
        #: the running process's start, and its latest counters (late_wakes, late_wake_ms)
        self._seen: tuple[float, int, float] = (0.0, 0, 0.0)

    def read(self, child: Child) -> None:
        try:
            mtime_ns = self.path.stat().st_mtime_ns
        except FileNotFoundError:
            return
        if mtime_ns == self._mtime_ns:
            return
        self._mtime_ns = mtime_ns
        try:
            status = json.loads(self.path.read_text())
        except (OSError, ValueError):
            return  # renamed over whole: not seen half written, but gone between stat and read
        t_s = status["t_ns"] / 1e9
        if t_s < child.started_at:
            return  # the previous process's last word
        stats = status["snapshot"]["stats"]
        count, late_ms = int(stats.get("late_wakes", 0)), float(stats.get("late_wake_ms", 0.0))
        started, seen, seen_ms = self._seen
        if started != child.started_at:  # a new process counts from zero
            seen, seen_ms = 0, 0.0
        if count > seen:
            self.wakes.append((t_s - (late_ms - seen_ms) / 1e3, t_s))
        self._seen = (child.started_at, count, late_ms)


class DeploymentError(RuntimeError):
    """The deployment did not come up: a process ended or never got ready (its log says why)."""


def _never(returncode: int) -> bool:
    """No unit ships for it: nothing starts it again."""
    return False


@dataclass
class Unit(Child):
    """One process of the deployment, as the supervisor keeps it (``deploy.supervisor.Child``)
    under its shipped unit's rules (``policy``), started by ``launcher``."""

    #: the shipped systemd unit's policy; None: no unit ships (a device, the network, a tool)
    policy: RestartPolicy | None = None
    launcher: Callable[[], Proc] | None = None
    #: the running process as the fleet started it (its log, stdin, stats)
    handle: Proc | None = None
    #: each clean restart: seconds from the stop signal to the end, and whether it was killed
    stops: list[tuple[float, bool]] = field(default_factory=list)

    @property
    def stop_posts(self) -> list[tuple[float, float, int]]:
        """(monotonic start, end, exit code) of each ExecStopPost= run."""
        return [] if self.stop_post is None else self.stop_post.runs

    def run_stop_post(self) -> None:
        """ExecStopPost= to its end (a clean restart: systemd runs it between stop and start)."""
        if self.stop_post is not None:
            self.stop_post.run(self.started_at)

    @property
    def pid(self) -> int:
        assert self.proc is not None
        return self.proc.pid

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None


def make_unit(
    name: str,
    launcher: Callable[[], Proc],
    rule: RestartPolicy | None,
    log_path: Path,
    **kw: Any,
) -> Unit:
    """A process under ``rule`` (its unit's RestartSec= and Restart=, never given up on),
    started by ``launcher`` (which may be replaced: a device's second start names its port)."""

    def start(_incarnation: int) -> subprocess.Popen:
        assert made.launcher is not None
        made.handle = made.launcher()
        made.log_path = made.handle.log_path
        return made.handle.popen

    made = Unit(
        name,
        start,
        log_path=log_path,
        restart_delay_s=0.0 if rule is None else rule.restart_sec,
        restart_on=_never if rule is None else rule.restarts_after,
        start_limit_burst=None,
        policy=rule,
        launcher=launcher,
        **kw,
    )
    return made


def _announcement(proc: Proc, timeout_s: float = 60.0) -> dict:
    """The JSON line a ``deepxpalm sim`` prints once it serves (its address)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for line in proc.log_text().splitlines():
            if line.startswith('{"simulator"'):
                return json.loads(line)
        if proc.popen.poll() is not None:
            break
        time.sleep(0.05)
    raise DeploymentError(f"{proc.name} did not start: {proc.log_text()[-2000:]}")


class Deployment:
    """The processes, their supervisor, and where each device can be read from outside.

    ``with Deployment(...) as d`` starts everything; leaving stops everything.
    ``outage_at_s``: the link's outage (5 s) starts this long after netsim does.
    """

    def __init__(self, workdir: Path | None = None, outage_at_s: float = NO_OUTAGE_AT_S) -> None:
        self.fleet = Fleet(robots=[ROBOT], operators={OPERATOR: "controller", RECORDER: "recorder"})
        if workdir is not None:
            self.fleet.workdir = workdir
        self.dir = self.fleet.workdir
        self.outage_at_s = outage_at_s
        self.outage_s = 5.0
        self.units: dict[str, Unit] = {}
        self.recording = self.dir / "recording.bin"
        self.stop_post_log = self.dir / "operator-stop-post.log"  # the palm lift's; in log_tails
        self.servo_status = self.dir / "servos-status.json"
        self.ur_host = ""
        self.gripper = ("127.0.0.1", 0)
        self.tactile_port = ""
        self.servo_port = ""
        self.video_url = ""
        #: netsim's UDP port the operator's QUIC connection goes to (it forwards to the router's)
        self.netsim_port = 0
        self._netsim_starts = 0  # each start writes its own ready file
        self.supervisor = Supervisor("deployment")
        self.late_wakes = LateWakes(self.dir / "operator-status.json")
        self._env_lock = threading.Lock()

    # ------------------------------------------------------------ starting
    def _sim(self, device: str, config: str, extra: list[str] | None = None) -> Proc:
        path = self.dir / f"sim-{device}.toml"
        path.write_text(config)
        log_path = self.dir / f"sim-{device}.log"
        args = ["sim", device, "--config", str(path), *(extra or [])]
        stats = self.dir / f"sim-{device}-stats.json"  # unused: a simulator writes none
        return Proc(f"sim-{device}", spawn_cli(args, log_path), log_path, stats)

    def _add(self, name: str, start: Callable[[], Proc], unit: str | None = None) -> Unit:
        rule = policy(unit) if unit else (DEVICE_BACK if name in DEVICES else None)
        made = make_unit(name, start, rule, self.dir / f"{name}.log")
        self.units[name] = made
        self.supervisor.add(made)
        return made

    def _start_netsim(self) -> Proc:
        scenario = self.dir / "scenario.toml"
        t1 = self.outage_at_s
        scenario.write_text(_SCENARIO_TOML.format(t1=t1, t2=t1 + self.outage_s))
        log_path = self.dir / "netsim.log"
        self._netsim_starts += 1
        ready = self.dir / f"netsim-ready-{self._netsim_starts}.json"
        args = [
            "-v",
            "netsim",
            *("--scenario", str(scenario), "--mode", "datagram"),
            # the router's side, and the operator's: one UDP address each (deploy/demo_fabric.py)
            *("--robot-telemetry", f"udp://127.0.0.1:{self.fleet.router_port}"),
            *("--operator-telemetry", f"udp://127.0.0.1:{self.netsim_port}"),
            *("--ready-file", str(ready)),
        ]
        return Proc("netsim", spawn_cli(args, log_path), log_path, self.dir / "netsim-stats.json")

    def start(self) -> Deployment:
        fleet = self.fleet
        self._add("router", fleet.start_router, "router")
        ur = self._add("ur", lambda: self._sim("ur", 'host = "auto"\n'))
        self.ur_host = _announcement(ur.handle)["host"]
        ur.launcher = lambda: self._sim("ur", f'host = "{self.ur_host}"\n')
        gripper = self._add("gripper", lambda: self._sim("gripper", "port = 0\n" + _PIPETTE))
        g = _announcement(gripper.handle)
        self.gripper = (g["host"], g["port"])
        at = f'host = "{g["host"]}"\nport = {g["port"]}\n'
        gripper.launcher = lambda: self._sim("gripper", at + _PIPETTE)
        board = _BOARD_TOML.format(link_dir=self.dir / "tactile-link")
        tactile = self._add("tactile", lambda: self._sim("tactile", board))
        self.tactile_port = _announcement(tactile.handle)["port"]
        bus = f'link_dir = "{self.dir / "servo-link"}"\n'
        status = ["--status-file", str(self.servo_status)]
        servos = self._add("servos", lambda: self._sim("servos", bus, status))
        self.servo_port = _announcement(servos.handle)["port"]
        video_port = free_loopback_ports(1)[0]
        self.video_url = fleet.video_url("video", video_port)
        self._add("video", lambda: fleet.start_video(port=video_port)[0], "video")
        devices = _ROBOT_DEVICES.format(
            tactile_port=self.tactile_port, gripper_host=g["host"], gripper_port=g["port"]
        )
        self._add(
            "robot",
            lambda: fleet.start_robot(
                ROBOT, self.ur_host, video_url=self.video_url, devices=devices
            ),
            "robot",
        )
        self.netsim_port = free_loopback_ports(1, udp=True)[0]
        self._add("netsim", self._start_netsim)
        self._add_operator()
        self._add("recorder", lambda: fleet.start_recorder(RECORDER, self.recording))
        self.supervisor.start_thread()
        return self

    def _add_operator(self) -> None:
        """The operator node under its unit's rules: its watchdog on the notify socket, and
        its ExecStopPost= (the palm lifted) with this deployment's config for /etc's."""
        rule = policy("operator")
        assert rule is not None
        watchdog = UnitWatchdog(
            self.dir / "operator.notify", rule.watchdog_sec, rule.timeout_abort_sec
        )
        config = self.fleet.workdir / f"{OPERATOR}@{ROBOT}.toml"  # what start_operator writes
        stop_post = stop_post_args(rule.stop_post, config)
        log_path = self.stop_post_log

        def start() -> Proc:
            with self._env_lock:  # the fleet starts every process with its env: this one's
                env = self.fleet.env
                self.fleet.env = {**env, **watchdog.environ()}
                try:
                    return self.fleet.start_operator(
                        OPERATOR,
                        ROBOT,
                        request_control=True,
                        want_frames=False,
                        servos=_SERVOS.format(port=self.servo_port, **simulated_driver_settings()),
                        router_endpoint=f"quic/127.0.0.1:{self.netsim_port}",
                        extra=["--status-file", str(self.late_wakes.path)],
                    )
                finally:
                    self.fleet.env = env

        self.units["operator"] = make_unit(
            "operator",
            start,
            rule,
            self.dir / "operator.log",
            # at the unit's Nice=, as systemd runs every command of the unit
            stop_post=StopPost(
                "operator", lambda: spawn_cli(["-v", *stop_post], log_path, "operator")
            ),
            watchdog=watchdog,
            watch=self.late_wakes.read,
        )
        self.supervisor.add(self.units["operator"])

    # ------------------------------------------------------------ faults
    def signal(self, name: str, sig: int) -> None:
        self.units[name].proc.send_signal(sig)

    def clean_restart(self, name: str, timeout_s: float = 20.0) -> float:
        """``systemctl restart``: stop (``processes.stop``), start again; the restart's time."""
        unit = self.units[name]
        self.supervisor.hold(name)
        try:
            t_term = time.monotonic()
            killed = stop(unit.proc, timeout_s)  # systemd's TimeoutStopSec=, then SIGKILL
            if killed:
                log.warning("%s still running %.0f s after its stop: killed", name, timeout_s)
            unit.stops.append((time.monotonic() - t_term, killed))
            unit.run_stop_post()
            unit.restart_times.append(time.monotonic())
            unit.incarnation += 1
            unit.spawn()
            started = time.monotonic()
        finally:
            self.supervisor.release(name)
        return started

    def netsim_started(self) -> list[float]:
        """When each netsim process began forwarding (monotonic s, its ready file), in order."""
        starts = []
        for n in range(1, self._netsim_starts + 1):
            try:
                ready = json.loads((self.dir / f"netsim-ready-{n}.json").read_text())
            except FileNotFoundError:
                continue  # that start has not forwarded yet, or never did
            starts.append(ready["schedule_start_ns"] / 1e9)
        return starts

    def operator_late_wakes(self) -> list[tuple[float, float]]:
        """Each time the operator's loop woke over 100 ms late: (due, woke), see ``LateWakes``."""
        return list(self.late_wakes.wakes)

    def outage_window(self) -> tuple[float, float] | None:
        """The scheduled outage on the monotonic clock, from netsim's own start time."""
        starts = self.netsim_started()
        if not starts:
            return None
        return starts[0] + self.outage_at_s, starts[0] + self.outage_at_s + self.outage_s

    def operator_send(self, command: dict) -> bool:
        """A JSON command to the operator node's stdin; False while it is down."""
        unit = self.units["operator"]
        if not unit.alive():
            return False
        try:
            unit.handle.send(command)
        except (BrokenPipeError, ValueError, OSError):
            return False
        return True

    def log_tails(self, chars: int = 1500) -> str:
        """Each unit's log tail, and its ExecStopPost's (the palm lift says why it failed)."""
        tails = [
            f"--- {n}\n{u.handle.log_text()[-chars:]}" for n, u in self.units.items() if u.handle
        ]
        if self.stop_post_log.exists():
            text = self.stop_post_log.read_text(errors="replace")
            tails.append(f"--- operator ExecStopPost\n{text[-chars:]}")
        return "\n".join(tails)

    # ------------------------------------------------------------ stopping
    def close(self) -> None:
        self.supervisor.close()
        order = ["recorder", "operator", "netsim", "robot", "video", "router"]
        order += ["servos", "tactile", "gripper", "ur"]
        for name in order:
            unit = self.units.get(name)
            if unit is None or unit.handle is None:
                continue
            popen = unit.proc
            if popen.poll() is None:
                popen.send_signal(signal.SIGCONT)  # a cell may end with it stopped
                stop(popen, 15)
            if unit.handle.stdin is not None:
                with contextlib.suppress(BrokenPipeError, OSError):
                    unit.handle.stdin.close()

    def __enter__(self) -> Deployment:
        try:
            return self.start()
        except BaseException:
            self.close()
            raise

    def __exit__(self, *exc: object) -> None:
        self.close()
