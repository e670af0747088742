"""``deepxpalm palm lift``: every LinkGlide linkage off the palm, from a process of its own.

The Feetech servos keep their last goal when the operator node dies: a node
killed (``kill -9``, a crash) or frozen while a stimulus pressed the palm
leaves the linkages pressing it. Any process that opens the bus once the node
is gone can lift them; this command is that process. It opens the servo bus
the operator's config names (the node's own driver, calibration and limits),
writes the node's own retract pose (``LinkGlideRenderer.retract_goals``), waits
until every servo reports it is there, and lets go as the node does on its
way out (torque off).

The operator's systemd unit runs it after every exit of the node
(``ExecStopPost=``, which runs after ``kill -9`` and after the watchdog ended
a frozen node too); the demo's supervisor runs it when the operator dies.

    deepxpalm palm lift --config /etc/deepxpalm/operator.toml

Exits 0 once the palm is free; 1 with what to do when it cannot be: the bus
is held by another process (a node still running), no servo answers, or a
servo did not reach the retract pose in time.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from common.errors import ConfigError, DeviceError

if TYPE_CHECKING:
    from operator_side.config import OperatorConfig
    from operator_side.servos.base import ServoBus

log = logging.getLogger(__name__)

#: a servo this close to its retract goal (counts, about 1.4 degrees) is off the palm
ARRIVED_COUNTS = 16
READ_PERIOD_S = 0.01


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from common.cli_support import add_overrides_argument

    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = __doc__
    parser.add_argument(
        "action", choices=["lift"], help="lift: write the retract pose and wait for it"
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


def lift(config: OperatorConfig, within_s: float = 2.0) -> dict[str, Any]:
    """Open the bus ``config.servos`` names, write the retract pose, wait, torque off.

    Returns what happened (ports, goals, how long); raises ``DeviceError`` with
    what to check when the palm could not be lifted.
    """
    from common.devices import build_device
    from operator_side.renderer import LinkGlideRenderer
    from operator_side.servos import KINDS

    kind = config.servos.get("kind")
    if kind != "feetech":
        raise ConfigError(
            f"operator.servos kind {kind!r} lives inside the node and ended with it: there is "
            'no bus left to lift. The palm\'s bus is kind = "feetech" (a simulated one runs '
            "as its own process: `deepxpalm sim servos`)"
        )
    servos: ServoBus = build_device(KINDS, config.servos, "operator.servos")  # type: ignore[assignment]
    t0 = time.monotonic()
    servos.connect()
    try:
        calibration = servos.calibration
        assert calibration is not None  # connect() loads it
        retract = LinkGlideRenderer(config.renderer, calibration).retract_goals
        goals = dict(zip((int(i) for i in calibration.ids), retract, strict=True))
        servos.write_goals(goals)
        written_s = time.monotonic() - t0
        present = _wait_for(servos, goals, within_s)
    finally:
        servos.disconnect()  # torque off, as the node leaves the palm on a clean stop
    return {
        "goals": goals,
        "present": present,
        "written_ms": round(written_s * 1e3),
        "arrived_ms": round((time.monotonic() - t0) * 1e3),
    }


def _wait_for(servos: ServoBus, goals: dict[int, int], within_s: float) -> dict[int, int]:
    """Present positions once every servo is within ``ARRIVED_COUNTS`` of its goal."""
    deadline = time.monotonic() + within_s
    while True:
        present = servos.read_positions()
        away = {i: present[i] for i in goals if abs(present[i] - goals[i]) > ARRIVED_COUNTS}
        if not away:
            return present
        if time.monotonic() > deadline:
            raise DeviceError(
                f"servos {sorted(away)} did not reach the retract pose within {within_s:g} s "
                f"(at {away}, goals {[goals[i] for i in sorted(away)]}); torque is now off, so "
                "they no longer press. Check for a blocked linkage, and goal_speed in "
                "[operator.servos]"
            )
        time.sleep(READ_PERIOD_S)


def run(args: argparse.Namespace) -> int:
    from common.cli_support import load_node_config
    from operator_side.config import OperatorConfig

    config = load_node_config(args, OperatorConfig, "operator")
    done = lift(config, args.within)
    port = config.servos.get("port", config.servos.get("kind"))
    print(
        f"palm lifted: servos {sorted(done['goals'])} at the retract pose on {port} "
        f"({done['written_ms']} ms to write it, {done['arrived_ms']} ms to arrive); torque off",
        flush=True,
    )
    return 0
