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
fresh process's start-up (``operator_side.palm.guard``). ``palm lift`` waits
while the guard holds the bus.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from common.errors import ConfigError
from operator_side.palm.lift import PalmConfig, lift


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from common.process.command_line import add_overrides_argument

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


def run(args: argparse.Namespace) -> int:
    from common.process.command_line import load_node_config

    config = load_node_config(args, PalmConfig, "operator", only=("renderer", "servos"))
    if args.action == "guard":
        if args.watch_fd is None:
            raise ConfigError(
                "palm guard watches the node's pipe: --watch-fd FD (the node "
                "starts it; run `deepxpalm palm lift` by hand instead)"
            )
        from operator_side.palm.guard import guard

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
