"""The shipped units as data: what starts each process, its rules, and what its READY=1 says.

One entry per kind of process the product runs: the two nodes, the fabric's
router, the video server, the recorder, the link simulator, the simulated lab
and the device simulators. For each: the ``deepxpalm`` arguments that start
it (the run adds its own config and files), the systemd unit whose rules it
runs under when one ships (``deploy/systemd/deepxpalm-<unit>.service``:
``Restart=``, ``RestartSec=``, ``WatchdogSec=``, ``Nice=``,
``ExecStopPost=``), and the endpoints its ``READY=1`` reports
(``X_DEEPXPALM_ENDPOINTS``). A process no unit ships for (the simulators, the
link simulator) comes back by itself after :data:`DEFAULT_RESTART_S`, as a
device's power or a network link does.

The demo, the fault matrix, the fleet, the soak and the bench start their
processes from here (``deploy.units.service.Service``), so a deployment on
one machine runs each process as systemd runs it on its own.
"""

from __future__ import annotations

from dataclasses import dataclass

from deploy.units.policy import RestartPolicy, policy

#: ``RestartSec=`` of a process no unit ships for: a device's power, the link, back
DEFAULT_RESTART_S = 1.0


@dataclass(frozen=True)
class UnitSpec:
    """One kind of process: how it starts, by which rules, what it says once ready."""

    name: str
    #: the ``deepxpalm`` arguments that start it, before the run's own (config, files)
    command: tuple[str, ...]
    what: str
    #: the keys of its READY=1's ``X_DEEPXPALM_ENDPOINTS`` (and other fields), and what they are
    ready: str
    #: the shipped systemd unit whose rules it runs under (``deepxpalm-<unit>.service``)
    unit: str | None = None
    #: its rules when no unit ships for it (None: back after DEFAULT_RESTART_S on failure)
    rules: RestartPolicy | None = None
    #: systemd's ``TimeoutStartSec=``: not ready by then, it is stopped (a loaded machine
    #: imports the robot's stack, warms its compiled step and connects its devices in it)
    start_timeout_s: float = 60.0
    #: it stands for what a site's shutdown leaves running (the network, another machine's
    #: router, the hardware): a deployment stops it after the nodes' processes, which stop
    #: together, as systemd stops units with no ordering between them
    outlives_the_nodes: bool = False

    @property
    def policy(self) -> RestartPolicy:
        """Its unit's rules; a process no unit ships for is restarted after any failure."""
        shipped = policy(self.unit) if self.unit else None
        if shipped is not None:
            return shipped
        if self.rules is not None:
            return self.rules
        return RestartPolicy(
            unit="", restart="on-failure", restart_sec=DEFAULT_RESTART_S, watchdog_sec=0.0
        )

    @property
    def stop_post(self) -> tuple[str, ...]:
        """Its unit's ``ExecStopPost=`` (``deepxpalm`` arguments; () for none)."""
        return self.policy.stop_post

    def argv(self, *args: str, verbose: bool = True) -> list[str]:
        """``deepxpalm [-v] COMMAND ARGS``."""
        return [*(["-v"] if verbose else []), *self.command, *args]


UNITS: dict[str, UnitSpec] = {
    spec.name: spec
    for spec in (
        UnitSpec(
            "robot",
            ("robot",),
            "the robot node: pads, gripper, arm, the link's robot end",
            "telemetry, commands: its link's bound endpoints (a direct link; port 0 binds a "
            "free one)",
            unit="robot",
        ),
        UnitSpec(
            "operator",
            ("operator",),
            "the operator node: the palm, the link's operator end, the dashboard",
            "dashboard: its page's address without the token (when it serves one)",
            unit="operator",
        ),
        UnitSpec(
            "router",
            ("router",),
            "the fabric's Zenoh router, its access control from the roster",
            "listen: its QUIC endpoint (port 0: a free one it chose)",
            unit="router",
            outlives_the_nodes=True,
        ),
        UnitSpec(
            "video",
            ("video",),
            "the video server: a camera to the dashboard over WebRTC",
            "signalling: its ws:// address without the token",
            unit="video",
        ),
        UnitSpec(
            "recorder",
            ("record",),
            "the recorder: every robot's stream, to a file",
            "source: the endpoint or router it reads; foxglove: its live view's ws:// address "
            "(when it serves one; port 0 binds a free one)",
        ),
        UnitSpec(
            "netsim",
            ("netsim",),
            "the link simulator between the robot (or router) and the operator",
            "operator_telemetry, operator_commands: where the operator connects (port 0 "
            "binds free ones); X_DEEPXPALM_SCHEDULE_START_NS: when its scenario's clock started",
            outlives_the_nodes=True,
        ),
        UnitSpec(
            "world",
            ("sim", "world"),
            "the simulated lab: the UR controller, the gripper, the pads, the camera",
            "ur_host, gripper_host, gripper_port, tactile_port, camera_port and the pads' "
            "calibration: a scene's running_world file",
            outlives_the_nodes=True,
        ),
        UnitSpec(
            "demo",
            ("demo",),
            "both nodes, their simulated devices and the link simulator on one machine",
            "logs: its directory; dashboard: the page's address without its token (when "
            "it serves one); READY=1 once every process of it said its own",
            start_timeout_s=240.0,
        ),
        *(
            UnitSpec(name, ("sim", kind), what, ready, outlives_the_nodes=True)
            for name, kind, what, ready in (
                ("sim-ur", "ur", "a UR controller's simulator", "host"),
                ("sim-gripper", "gripper", "a Robotiq URCap's simulator", "host, port"),
                ("sim-tactile", "tactile", "the tactile board's simulator", "port (pty)"),
                ("sim-servos", "servos", "the palm's servo bus simulator", "port (pty)"),
            )
        ),
    )
}


def unit(name: str) -> UnitSpec:
    """The catalogue's entry for ``name`` (KeyError naming the known ones)."""
    try:
        return UNITS[name]
    except KeyError:
        raise KeyError(f"no unit {name!r} in the catalogue: {', '.join(UNITS)}") from None
