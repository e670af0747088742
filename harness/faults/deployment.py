"""Every process of a deployment on this machine, each started as on its own machine.

The fabric's router, the robot node, the operator node, the recorder and the
video server run as ``harness.fleet`` starts them (QUIC with the members'
certificates, a roster, signed commands); the robot and the recorder connect
to the router directly, the operator through ``deepxpalm netsim`` in datagram
mode (its QUIC connection's UDP crosses the link, as over a real network);
every device is a simulator in a process of its own (``deepxpalm sim
ur|gripper|tactile|servos``) so that killing a node never kills its device. Each
is a unit of the product's catalogue (``deploy.units``): it binds port 0 and
says where in its ``READY=1``, and the processes that need that address are
started after it. The demo's supervisor (``deploy.units.supervisor``) plays
systemd on a thread of its own: a process of a shipped unit that ends is
started again after the unit's RestartSec= when its Restart= says so (on the
address it had), runs its ExecStopPost= after any end (the operator's lifts
the palm), and ends a process whose WatchdogSec= passed without a ping
(``deploy.units.watchdog.UnitWatchdog``).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from deploy.units.catalogue import unit as catalogue_unit
from deploy.units.child import Child, StopPost
from deploy.units.policy import RestartPolicy
from deploy.units.readiness import NotReady, Ready
from deploy.units.service import Service
from deploy.units.supervisor import Supervisor
from harness.fleet import Fleet, Proc
from operator_side.servos.sts_sim import simulated_driver_settings

log = logging.getLogger(__name__)

ROBOT, OPERATOR, RECORDER = "cell", "op", "rec"
#: the fault target that is the robot node's arm process (robot_side/arm/process)
ARM_PROCESS = "arm"

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

#: the link: a wired LAN carrying the operator's QUIC datagrams (the fabric); ``cut_link``
#: pulls its cable (every datagram lost, both ways) for ``OUTAGE_S``
_SCENARIO_TOML = """
name = "lan-fabric"
description = "wired LAN carrying the fabric's QUIC datagrams (the fault matrix)"
[both]
delivery = "datagram"
delay_ms = 0.1
jitter_ms = 0.02
distribution = "normal"
"""
OUTAGE_S = 5.0

#: hardware and the network come back by themselves: a device's power, the link. The
#: supervisor (a thread that lives as long as the deployment) starts them again, because a
#: child's PR_SET_PDEATHSIG follows the *thread* that forked it: one forked from a short
#: thread would be sent its death signal the moment that thread ends
DEVICE_BACK = RestartPolicy(unit="", restart="on-failure", restart_sec=2.0, watchdog_sec=0.0)
DEVICES = ("ur", "gripper", "tactile", "servos", "netsim")


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
    """One process of the deployment, as the supervisor keeps it (``deploy.units.supervisor``)
    under its shipped unit's rules (``policy``)."""

    #: the shipped systemd unit's policy; None: no unit ships (a tool: nothing restarts it)
    policy: RestartPolicy | None = None
    #: the process as the fleet made it (its log, stdin, stats)
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


def make_unit(name: str, proc: Proc, rule: RestartPolicy | None, **kw: Any) -> Unit:
    """The fleet's process ``proc`` under ``rule`` (its unit's RestartSec= and Restart=, never
    given up on); None: nothing restarts it. Called ``name`` by the supervisor (``hold``)."""
    proc.service.name = name
    return Unit(
        proc.service,
        restart_delay_s=0.0 if rule is None else rule.restart_sec,
        restart_on=_never if rule is None else rule.restarts_after,
        start_limit_burst=None,
        policy=rule,
        handle=proc,
        **kw,
    )


def _pin(service: Service, wildcard: str, bound: str) -> None:
    """A restart of ``service`` binds ``bound`` where its first start asked for ``wildcard``
    (port 0), so its peers find it again."""
    argv = service.argv(0)
    service.argv = lambda _n: [bound if a == wildcard else a for a in argv]


class Deployment:
    """The processes, their supervisor, and where each device can be read from outside.

    ``with Deployment(...) as d`` starts everything; leaving stops everything.
    """

    def __init__(self, workdir: Path | None = None) -> None:
        self.fleet = Fleet(robots=[ROBOT], operators={OPERATOR: "controller", RECORDER: "recorder"})
        if workdir is not None:
            self.fleet.workdir = workdir
        self.dir = self.fleet.workdir
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
        self.supervisor = Supervisor("deployment")
        self.late_wakes = LateWakes(self.dir / "operator-status.json")

    # ------------------------------------------------------------ starting
    def _sim(self, device: str, config: str, extra: list[str] | None = None) -> Proc:
        """``deepxpalm sim DEVICE`` with ``config``; its READY=1 says where it serves."""
        path = self.dir / f"sim-{device}.toml"
        path.write_text(config)
        args = ["sim", device, "--config", str(path), *(extra or [])]
        return self.fleet.process(f"sim-{device}", f"sim-{device}", args, stats=False)

    def _add(
        self,
        name: str,
        proc: Proc,
        ready: bool = True,
        after_ready: Callable[[Ready], None] | None = None,
        **kw: Any,
    ) -> Unit:
        """``proc`` under its unit's rules (a device's and the link's: back after
        ``DEVICE_BACK``; anything else no unit ships for: never restarted); with ``ready``,
        once it said READY=1."""
        spec = proc.service.spec
        rule = spec.policy if spec.unit else (DEVICE_BACK if name in DEVICES else None)
        made = make_unit(name, proc, rule, after_ready=after_ready, **kw)
        self.units[name] = made
        try:
            self.supervisor.add(made, ready=ready)
        except NotReady as e:
            raise DeploymentError(str(e)) from None
        return made

    def start(self) -> Deployment:
        fleet = self.fleet
        router = fleet.router()
        self._add("router", router, after_ready=fleet.router_ready)

        def ur_up(ready: Ready) -> None:  # a restarted controller keeps its address
            self.ur_host = ready.endpoints["host"]
            (self.dir / "sim-ur.toml").write_text(f'host = "{self.ur_host}"\n')

        self._add("ur", self._sim("ur", 'host = "auto"\n'), after_ready=ur_up)

        def gripper_up(ready: Ready) -> None:
            self.gripper = (ready.endpoints["host"], ready.endpoints["port"])
            at = f'host = "{self.gripper[0]}"\nport = {self.gripper[1]}\n'
            (self.dir / "sim-gripper.toml").write_text(at + _PIPETTE)

        self._add("gripper", self._sim("gripper", "port = 0\n" + _PIPETTE), after_ready=gripper_up)
        board = _BOARD_TOML.format(link_dir=self.dir / "tactile-link")
        tactile = self._add("tactile", self._sim("tactile", board))
        self.tactile_port = tactile.service.ready.endpoints["port"]
        bus = f'link_dir = "{self.dir / "servo-link"}"\n'
        status = ["--status-file", str(self.servo_status)]
        servos = self._add("servos", self._sim("servos", bus, status))
        self.servo_port = servos.service.ready.endpoints["port"]
        video = fleet.video()

        def video_up(ready: Ready) -> None:
            self.video_url = fleet.video_url("video", ready)
            port = ready.endpoints["signalling"].rstrip("/").rpartition(":")[2]
            _pin(video.service, "port=0", f"port={port}")

        self._add("video", video, after_ready=video_up)
        devices = _ROBOT_DEVICES.format(
            tactile_port=self.tactile_port,
            gripper_host=self.gripper[0],
            gripper_port=self.gripper[1],
        )
        robot = fleet.robot(ROBOT, self.ur_host, video_url=self.video_url, devices=devices)
        self._add("robot", robot, ready=False)  # it connects to the router: nobody waits
        self._add("netsim", self._netsim(), after_ready=self._netsim_up)
        self._add_operator()
        self._add("recorder", fleet.recorder(RECORDER, self.recording), ready=False)
        for name in ("robot", "operator", "recorder"):  # up: every process said READY=1
            try:
                self.units[name].wait_ready()
            except NotReady as e:
                raise DeploymentError(str(e)) from None
        self.supervisor.start_thread()
        return self

    def _netsim(self) -> Proc:
        scenario = self.dir / "scenario.toml"
        scenario.write_text(_SCENARIO_TOML)
        router_udp = "udp://" + self.fleet.router_endpoint.removeprefix("quic/")
        args = [
            "-v",
            "netsim",
            *("--scenario", str(scenario), "--mode", "datagram"),
            *("--set", f"netsim.cut_s={OUTAGE_S}"),
            # the router's side, and the operator's: one UDP address each (deploy/demo_fabric.py)
            *("--robot-telemetry", router_udp, "--operator-telemetry", "udp://127.0.0.1:0"),
        ]
        return self.fleet.process("netsim", "netsim", args)

    def _netsim_up(self, ready: Ready) -> None:
        """The operator's side of the link (a restarted netsim binds it again)."""
        bound = ready.endpoints["operator_telemetry"]
        self.netsim_port = int(bound.rpartition(":")[2])
        _pin(self.units["netsim"].service, "udp://127.0.0.1:0", bound)

    def _add_operator(self) -> None:
        """The operator node under its unit's rules: its watchdog on its notify socket, and
        its ExecStopPost= (the palm lifted) with this deployment's config for /etc's."""
        proc = self.fleet.operator(
            OPERATOR,
            ROBOT,
            request_control=True,
            want_frames=False,
            servos=_SERVOS.format(port=self.servo_port, **simulated_driver_settings()),
            router_endpoint=f"quic/127.0.0.1:{self.netsim_port}",
            extra=["--status-file", str(self.late_wakes.path)],
            watchdog=True,
        )
        config = self.fleet.workdir / f"{OPERATOR}@{ROBOT}.toml"  # what operator() writes
        self._add(
            "operator",
            proc,
            ready=False,
            stop_post=StopPost.of(catalogue_unit("operator"), config, self.stop_post_log),
            watch=self.late_wakes.read,
        )

    # ------------------------------------------------------------ faults
    def signal(self, name: str, sig: int) -> None:
        if name == ARM_PROCESS:
            os.kill(self.arm_process_pid(), sig)
            return
        self.units[name].proc.send_signal(sig)

    def arm_process_pid(self) -> int:
        """The robot node's arm process (the UR driver's real-time duties): its child running
        ``robot_side.arm.process``; no unit of its own (the node's recovery starts another)."""
        from harness.processes import children_of, cmdline

        robot = self.units["robot"].proc.pid
        for pid in children_of(robot):
            if "robot_side.arm.process" in (cmdline(pid) or []):
                return pid
        raise DeploymentError(f"the robot node (pid {robot}) has no arm process")

    def clean_restart(self, name: str, timeout_s: float = 20.0) -> float:
        """``systemctl restart``: stop (``Service.stop``), start again; the restart's time."""
        unit = self.units[name]
        self.supervisor.hold(name)
        try:
            t_term = time.monotonic()
            killed = unit.service.stop(timeout_s)  # systemd's TimeoutStopSec=, then SIGKILL
            if killed:
                log.warning("%s still running %.0f s after its stop: killed", name, timeout_s)
            unit.stops.append((time.monotonic() - t_term, killed))
            unit.run_stop_post()
            unit.restart_times.append(time.monotonic())
            unit.spawn()
            started = time.monotonic()
        finally:
            self.supervisor.release(name)
        return started

    def netsim_started(self) -> list[float]:
        """When each netsim process began forwarding (monotonic s, its READY=1), in order."""
        unit = self.units.get("netsim")
        if unit is None:
            return []
        return [
            int(ready.field("schedule_start_ns")) / 1e9 for ready in unit.service.notify.readies()
        ]

    def operator_late_wakes(self) -> list[tuple[float, float]]:
        """Each time the operator's loop woke over 100 ms late: (due, woke), see ``LateWakes``."""
        return list(self.late_wakes.wakes)

    def cut_link(self, timeout_s: float = 5.0) -> tuple[float, float]:
        """Pull the link's cable for ``OUTAGE_S`` (netsim's SIGUSR1): the cut's window on the
        monotonic clock, as netsim applied it (its ``X_DEEPXPALM_CUT_NS``)."""
        notify = self.units["netsim"].service.notify
        before = notify.field("cut_ns")
        self.units["netsim"].proc.send_signal(signal.SIGUSR1)
        said = notify.wait_field("cut_ns", before, timeout_s)
        if said is None:
            raise DeploymentError(f"netsim never said it cut the link within {timeout_s:g} s")
        t1, t2 = (int(t) / 1e9 for t in said.split(","))
        return t1, t2

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
        """Every process stopped as systemd stops the units: the nodes' together, then the
        router, the link and the device simulators (a cell may end with one stopped: the
        stop continues it)."""
        self.supervisor.close()
        errors: list[str] = []
        self.supervisor.stop_all(errors, timeout_s=15.0)
        for error in errors:
            log.info("deployment: %s", error)
        for unit in self.units.values():
            stdin = unit.handle.stdin if unit.handle is not None else None
            if stdin is not None:
                with contextlib.suppress(BrokenPipeError, OSError):
                    stdin.close()

    def __enter__(self) -> Deployment:
        try:
            return self.start()
        except BaseException:
            self.close()
            raise

    def __exit__(self, *exc: object) -> None:
        self.close()
