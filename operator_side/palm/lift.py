"""The palm's lift: every LinkGlide linkage off the palm, from a process that is not the node.

What ``deepxpalm palm lift`` runs after the node's end, and what the node's
palm guard runs the moment it ends (``operator_side.palm.guard``): open the
servo bus the operator's config names (the node's own driver, calibration
and limits), write the node's own retract pose as the port opens
(``FeetechServoBus.connect(first_goals=...)``), check every servo, wait
until every servo reports it is there (``ServoBus.wait_for_arrival``), and
let go as the node does on its way out (torque off).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from common.config.typed import param
from common.errors import ConfigError, DeviceError
from operator_side.palm.renderer_config import RendererConfig

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
    servos: dict[str, Any] = param({"kind": "in_memory"}, "LinkGlide servo bus: kind + settings")


def lift(config: PalmConfig, within_s: float = 2.0, bus_wait_s: float = 0.0) -> dict[str, Any]:
    """Open the bus ``config.servos`` names, write the retract pose, wait, torque off.

    A bus another process holds is tried again for up to ``bus_wait_s`` (the
    palm guard lifting it; a node on its way out).

    Returns what happened (ports, goals, how long); raises ``DeviceError`` with
    what to check when the palm could not be lifted.
    """
    from common.devices.lifecycle import build_device
    from operator_side.palm.renderer_config import retract_goals
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
