"""``deepxpalm palm lift``: every LinkGlide linkage off the palm, from a process of its own.

The Feetech servos keep their last goal when the operator node dies: a node
killed (``kill -9``, a crash) or frozen while a stimulus pressed the palm
leaves the linkages pressing it. Any process that opens the bus once the node
is gone can lift them; this command is that process. It opens the servo bus
the operator's config names (the node's own driver, calibration and limits),
writes the node's own retract pose (``renderer_config.retract_goals``), waits
until every servo reports it is there (``ServoBus.wait_for_arrival``), and lets
go as the node does on its way out (torque off).

The operator's systemd unit runs it after every exit of the node
(``ExecStopPost=``, which runs after ``kill -9`` and after the watchdog ended
a frozen node too); the demo's supervisor runs it when the operator dies.

    deepxpalm palm lift --config /etc/deepxpalm/operator.toml

Exits 0 once the palm is free; 1 with what to do when it cannot be: the bus
is held by another process for longer than ``--wait-for-bus`` (a node still
running), no servo answers, or a servo did not reach the retract pose in
time.

``deepxpalm palm guard`` is the same lift started ahead of time: the node
starts it beside itself, and it lifts the moment the node ends, without a
fresh process's start-up (``operator_side.palm_guard``). ``palm lift`` waits
while the guard holds the bus.
"""

from __future__ import annotations

import argparse
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from common.config import param
from common.errors import ConfigError, DeviceError
from operator_side.renderer_config import RendererConfig

if TYPE_CHECKING:
    from operator_side.servos.feetech import FeetechServoBus

log = logging.getLogger(__name__)


@dataclass
class PalmConfig:
    """What the lift reads of the operator's config: the servo bus and the renderer's
    settings (the retract point and the linkages). The rest of the node's config is
    not read, nor are its parts imported (ZeroMQ, the dashboard, NumPy): this
    process's start-up is the time a dead node's linkages stay on the palm."""

    renderer: RendererConfig = param(RendererConfig(), "the retract point and the linkages")
    servos: dict[str, Any] = param({"kind": "recording"}, "LinkGlide servo bus: kind + settings")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from common.cli_support import add_overrides_argument

    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = __doc__
    parser.add_argument(
        "action",
        choices=["lift", "guard"],
        help="lift: write the retract pose and wait for it; guard: the same once the node "
        "whose pipe --watch-fd is ends (the node starts it)",
    )
    parser.add_argument(
        "--config", type=Path, help="the operator's TOML config (or a scene file): its servos"
    )
    add_overrides_argument(parser, 'operator.servos.port="/dev/ttyUSB1"')
    parser.add_argument(
        "--within",
        type=float,
        default=2.0,
        metavar="S",
        help="longest wait for every servo to reach the retract pose (default: 2 s)",
    )
    parser.add_argument(
        "--wait-for-bus",
        type=float,
        default=5.0,
        metavar="S",
        help="longest wait while another process holds the bus, as the node's palm guard does "
        "while it lifts (default: 5 s)",
    )
    parser.add_argument(
        "--watch-fd",
        type=int,
        metavar="FD",
        help="guard: the pipe whose end (the node's) starts the lift",
    )


def lift(config: PalmConfig, within_s: float = 2.0, bus_wait_s: float = 0.0) -> dict[str, Any]:
    """Open the bus ``config.servos`` names, write the retract pose, wait, torque off.

    A bus another process holds is tried again for up to ``bus_wait_s`` (the
    palm guard lifting it; a node on its way out).

    Returns what happened (ports, goals, how long); raises ``DeviceError`` with
    what to check when the palm could not be lifted.
    """
    from common.devices import build_device
    from operator_side.renderer_config import retract_goals
    from operator_side.servos import KINDS

    kind = config.servos.get("kind")
    if kind != "feetech":
        raise ConfigError(
            f"operator.servos kind {kind!r} lives inside the node and ended with it: there is "
            'no bus left to lift. The palm\'s bus is kind = "feetech" (a simulated one runs '
            "as its own process: `deepxpalm sim servos`)"
        )
    servos: FeetechServoBus = build_device(KINDS, config.servos, "operator.servos")  # type: ignore[assignment]
    calibration = servos.configured_calibration()
    goals = dict(zip(calibration.id_list, retract_goals(config.renderer, calibration), strict=True))
    t0 = time.monotonic()
    _connect(servos, goals, bus_wait_s)  # the goals go out first, the checks after them
    try:
        checked_s = time.monotonic() - t0
        away = servos.wait_for_arrival(goals, within_s)
        if away:
            raise DeviceError(
                f"servos {sorted(away)} did not reach the retract pose within {within_s:g} s "
                f"(at {away}, goals {[goals[i] for i in sorted(away)]}); torque is now off, so "
                "they no longer press. Check for a blocked linkage, and goal_speed in "
                "[operator.servos]"
            )
    finally:
        servos.disconnect()  # torque off, as the node leaves the palm on a clean stop
    return {
        "goals": goals,
        "checked_ms": round(checked_s * 1e3),
        "arrived_ms": round((time.monotonic() - t0) * 1e3),
    }


def _connect(servos: FeetechServoBus, goals: dict[int, int], bus_wait_s: float) -> None:
    from operator_side.servos.feetech import PortBusyError

    deadline = time.monotonic() + bus_wait_s
    while True:
        try:
            servos.connect(first_goals=goals)
            return
        except PortBusyError:
            if time.monotonic() >= deadline:
                raise
            time.sleep(0.01)


def run(args: argparse.Namespace) -> int:
    from common.cli_support import load_node_config

    config = load_node_config(args, PalmConfig, "operator", only=("renderer", "servos"))
    if args.action == "guard":
        if args.watch_fd is None:
            raise ConfigError(
                "palm guard watches the node's pipe: --watch-fd FD (the node "
                "starts it; run `deepxpalm palm lift` by hand instead)"
            )
        from operator_side.palm_guard import guard

        done = guard(config, args.watch_fd, args.within)
        what = "palm guard: the node ended, palm lifted"
    else:
        done = lift(config, args.within, args.wait_for_bus)
        what = "palm lifted"
    port = config.servos.get("port", config.servos.get("kind"))
    print(
        f"{what}: servos {sorted(done['goals'])} at the retract pose on {port} "
        f"({done['checked_ms']} ms to write it and hear every servo, {done['arrived_ms']} ms to "
        "arrive); torque off",
        flush=True,
    )
    return 0
