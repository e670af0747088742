"""LinkGlide rendering: stimulus -> contact points -> IK -> servo counts, rate limited.

This is the operator's hot path, and everything a servo is told passes
through ``step``: counts are always finite, inside the calibrated limits,
and never more than one cycle's step from what was last commanded.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from common.errors import ConfigError
from operator_side.palm.contact import reachable_set, stimulus_to_points
from operator_side.palm.linkglide import (
    UnreachableTargetError,
    inverse_kinematics,
    inverse_kinematics_one,
)

# the settings and the retract pose, where `deepxpalm palm lift` reads them without NumPy
from operator_side.palm.renderer_config import RendererConfig, retract_goals, retract_pose
from operator_side.servos.calibration import COUNTS_PER_RAD, LinkGlideCalibration

log = logging.getLogger(__name__)


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
        self._retract_pose = retract_pose(config)
        #: six goal counts (ids 1..6) with every linkage off the palm
        self.retract_goals = retract_goals(config, calibration)
        self.retract_angles = np.array(self._retract_pose).reshape(3, 2)
        self.retract_counts = np.array(self.retract_goals, dtype=np.int64)

    # The node's loop works on six plain numbers (NumPy's per-call cost is
    # many times the arithmetic at this size); the array forms wrap them.

    def pose_for(self, stimulus: np.ndarray | None) -> list[float]:
        """Six angles (tau_a, tau_e per linkage); ``None`` (no fresh stimulus) lifts all off."""
        pose = self._retract_pose.copy()
        if stimulus is None:
            return pose
        for n, (x, y) in enumerate(stimulus_to_points(stimulus, self.config.contact)):
            try:
                pose[2 * n : 2 * n + 2] = inverse_kinematics_one(x, y, self.geometry)
            except UnreachableTargetError as e:  # cannot happen with a validated mapping
                log.error("linkage %d: %s; lifting it off", n, e)
        return pose

    def goals_for(self, stimulus: np.ndarray | None) -> list[int]:
        """Six goal counts for ids 1..6: ``pose_for`` through the calibration."""
        return self.calibration.counts_for(self.pose_for(stimulus))

    def step_goals(self, current: list[int], target: list[int], fraction: float = 1.0) -> list[int]:
        """Move from ``current`` toward ``target`` by at most one cycle's step.

        ``fraction`` scales the step for a cycle shorter than the nominal one,
        so event-driven updates keep the same speed limit.
        """
        limit = max(1, round(self.max_step_counts * min(max(fraction, 0.0), 1.0)))
        moved = [c + min(max(t - c, -limit), limit) for c, t in zip(current, target, strict=True)]
        return self.calibration.clip_list(moved)

    def target_angles(self, stimulus: np.ndarray | None) -> np.ndarray:
        """(3, 2) angles; ``None`` (no fresh stimulus) lifts every linkage off."""
        return np.array(self.pose_for(stimulus)).reshape(3, 2)

    def target_counts(self, stimulus: np.ndarray | None) -> np.ndarray:
        return np.array(self.goals_for(stimulus), dtype=np.int64)

    def step(self, current: np.ndarray, target: np.ndarray, fraction: float = 1.0) -> np.ndarray:
        """``step_goals`` for arrays."""
        moved = self.step_goals(np.asarray(current).tolist(), np.asarray(target).tolist(), fraction)
        return np.array(moved, dtype=np.int64)
