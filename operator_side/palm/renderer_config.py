"""The renderer's settings, and the retract pose they give, in plain numbers (no NumPy).

``LinkGlideRenderer`` lifts every linkage off the palm with ``retract_goals``;
``deepxpalm palm lift`` writes the same goals after the node died, from a
process whose start-up is the time the dead node's linkages stay on the
palm: hence no NumPy (half a second to import) on this path.
"""

from __future__ import annotations

from dataclasses import dataclass

from common.config.typed import param
from operator_side.palm.contact import ContactMapping
from operator_side.palm.linkage import LinkageGeometry, inverse_kinematics_one
from operator_side.servos.calibration import LinkGlideCalibration


@dataclass
class RendererConfig:
    contact: ContactMapping = param(ContactMapping(), "stimulus to contact point mapping")
    geometry: LinkageGeometry = param(LinkageGeometry(), "link lengths of all three linkages")
    max_step_deg_per_cycle: float = param(
        4.0, "largest goal change per servo per palm step: a jump becomes a short motion"
    )
    palm_step_rate_hz: float = param(60.0, "servo goal updates per second")


def retract_pose(config: RendererConfig) -> list[float]:
    """Six angles (tau_a, tau_e per linkage) with every contact at the retract point."""
    x, y = config.contact.retract_point_mm
    return list(inverse_kinematics_one(x, y, config.geometry)) * 3


def retract_goals(config: RendererConfig, calibration: LinkGlideCalibration) -> list[int]:
    """Six goal counts (ids 1..6) with every linkage off the palm."""
    return calibration.counts_for(retract_pose(config))
