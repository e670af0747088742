"""LinkGlide rendering: stimulus -> contact points -> IK -> servo counts, rate limited.

This is the operator's hot path, and everything a servo is told passes
through ``step``: counts are always finite, inside the calibrated limits,
and never more than one cycle's step from what was last commanded.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from common.config import param
from common.errors import ConfigError
from operator_side.contact import ContactMapping, reachable_set, stimulus_to_points
from operator_side.linkglide import (
    LinkageGeometry,
    UnreachableTargetError,
    inverse_kinematics,
    inverse_kinematics_one,
)
from operator_side.servos.calibration import COUNTS_PER_RAD, LinkGlideCalibration

log = logging.getLogger(__name__)


@dataclass
class RendererConfig:
    contact: ContactMapping = param(ContactMapping(), "stimulus to contact point mapping")
    geometry: LinkageGeometry = param(LinkageGeometry(), "link lengths of all three linkages")
    max_step_deg_per_cycle: float = param(
        4.0, "largest goal change per servo per control cycle: a jump becomes a short motion"
    )
    control_rate_hz: float = param(60.0, "servo goal updates per second")


class LinkGlideRenderer:
    """Turns stimuli into rate-limited goal counts for servo ids 1..6."""

    def __init__(self, config: RendererConfig, calibration: LinkGlideCalibration) -> None:
        self.config = config
        self.calibration = calibration
        self.geometry = config.geometry
        if not config.max_step_deg_per_cycle > 0:
            raise ConfigError("max_step_deg_per_cycle must be positive")
        self.max_step_counts = max(
            1, round(math.radians(config.max_step_deg_per_cycle) * COUNTS_PER_RAD)
        )
        try:
            inverse_kinematics(reachable_set(config.contact), config.geometry)
        except UnreachableTargetError as e:
            raise ConfigError(
                f"the contact mapping asks for a point LinkGlide cannot reach: {e}"
            ) from None
        rx, ry = config.contact.retract_point_mm
        self.retract_angles = np.array([inverse_kinematics_one(rx, ry, self.geometry)] * 3)
        self.retract_counts = calibration.angles_to_counts(self.retract_angles)

    def target_angles(self, stimulus: np.ndarray | None) -> np.ndarray:
        """(3, 2) angles; ``None`` (no fresh stimulus) lifts every linkage off."""
        if stimulus is None:
            return self.retract_angles.copy()
        out = self.retract_angles.copy()
        for n, (x, y) in enumerate(stimulus_to_points(stimulus, self.config.contact)):
            try:
                out[n] = inverse_kinematics_one(x, y, self.geometry)
            except UnreachableTargetError as e:  # cannot happen with a validated mapping
                log.error("linkage %d: %s; lifting it off", n, e)
        return out

    def target_counts(self, stimulus: np.ndarray | None) -> np.ndarray:
        return self.calibration.angles_to_counts(self.target_angles(stimulus))

    def step(self, current: np.ndarray, target: np.ndarray, fraction: float = 1.0) -> np.ndarray:
        """Move from ``current`` toward ``target`` by at most one cycle's step.

        ``fraction`` scales the step for a cycle shorter than the nominal one,
        so event-driven updates keep the same speed limit.
        """
        limit = max(1, round(self.max_step_counts * min(max(fraction, 0.0), 1.0)))
        moved = [
            c + min(max(t - c, -limit), limit)
            for c, t in zip(np.asarray(current).tolist(), np.asarray(target).tolist(), strict=True)
        ]
        return np.array(self.calibration.clip_list(moved), dtype=np.int64)
