"""The arm's safety envelope: the workspace box, the speed caps and what a jog may do.

Poses are ``[x, y, z, rx, ry, rz]`` in the robot base frame: metres and a
rotation vector in radians (UR's convention). Velocities are
``[vx, vy, vz, wx, wy, wz]`` in m/s and rad/s. A jog is clipped to the speed
limits and loses any component that would leave the workspace box before
the deadman could stop it (``clip_jog_velocity``), a function of the limits
alone, so an exporter can apply it to recorded commands.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from common.config.typed import param
from common.errors import ConfigError, DeviceError
from common.rotation import rotation_angle, rotvec_to_matrix


class WorkspaceLimitError(DeviceError):
    """A move target lies outside the configured workspace box."""


@dataclass
class ArmLimits:
    """Where the TCP may go and how fast: the lab's safety envelope."""

    workspace_min: tuple[float, float, float] = param(
        (-0.40, -0.40, 0.05),
        "lowest x, y, z (m, base frame) the TCP may reach; z keeps the gripper off the table",
    )
    workspace_max: tuple[float, float, float] = param(
        (0.40, 0.40, 0.50), "highest x, y, z (m); inside the UR3e's 0.5 m reach"
    )
    max_linear_speed_m_s: float = param(
        0.10, "jog and move speed cap: slow enough to stop before a pipette rack"
    )
    max_angular_speed_rad_s: float = param(0.5, "jog rotation cap (about 30 deg/s)")
    linear_acceleration_m_s2: float = param(0.5, "acceleration for jogs and moves")
    stop_deceleration_m_s2: float = param(
        2.0,
        "deceleration of every stop (arm_stop, deadman, jog expiry): 50 ms and 2.5 mm from "
        "the speed cap; ur_rtde's own speedStop default is 10. A turning wrist stops harder "
        "(URArm: within half its watchdog window)",
    )
    angular_acceleration_rad_s2: float = param(
        1.0,
        "rotational acceleration for jogs: a pure wrist turn ramps at it; a jog that also "
        "translates at the lower of this and linear_acceleration_m_s2 (URArm: speedL has one)",
    )
    default_move_speed_m_s: float = param(0.05, "move_to speed when the caller gives none")
    jog_timeout_s: float = param(
        0.25, "a jog stops this long after the last jog command (deadman on a lost link)"
    )

    def __post_init__(self) -> None:
        lo, hi = self.workspace_min, self.workspace_max
        if any(a >= b for a, b in zip(lo, hi, strict=True)):
            raise ConfigError(
                f"arm workspace_min {lo} must be below workspace_max {hi} on every axis"
            )
        for name in (
            "max_linear_speed_m_s",
            "max_angular_speed_rad_s",
            "linear_acceleration_m_s2",
            "angular_acceleration_rad_s2",
            "stop_deceleration_m_s2",
            "default_move_speed_m_s",
            "jog_timeout_s",
        ):
            if not getattr(self, name) > 0:
                raise ConfigError(f"arm {name} must be positive")
        if self.default_move_speed_m_s > self.max_linear_speed_m_s:
            raise ConfigError("arm default_move_speed_m_s must not exceed max_linear_speed_m_s")

    def contains(self, xyz: Sequence[float]) -> bool:
        bounds = zip(self.workspace_min, self.workspace_max, strict=True)
        return all(lo <= v <= hi for v, (lo, hi) in zip(xyz, bounds, strict=True))


def turn_angle(a: np.ndarray, b: np.ndarray) -> float:
    """Angle (rad) between two orientations given as rotation vectors."""
    return rotation_angle(rotvec_to_matrix(a), rotvec_to_matrix(b))


def as_vector6(value: Sequence[float], what: str) -> np.ndarray:
    arr = np.asarray(value, dtype=float).reshape(-1)
    if arr.shape != (6,):
        raise ValueError(f"{what} must have 6 numbers, not {arr.shape[0]}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{what} must be finite, not {arr.tolist()}")
    return arr


#: the time a deadman stop takes to reach the controller, and the thread's own lateness
STOP_TRANSIT_S = 0.03


def deadman_period_s(limits: ArmLimits) -> float:
    """How often the deadman thread wakes: its jog check and ``_keep_alive`` run this often."""
    return min(0.02, limits.jog_timeout_s / 5)


def jog_overdue_s(limits: ArmLimits) -> float:
    """How long past its deadline a jog may still run before it counts as overdue: the
    deadman's wake period and the stop's transit. An overdue jog means a starved deadman,
    and a keep-alive stops vouching for it (``SafetyThreads.deadman_responsive``)."""
    return deadman_period_s(limits) + STOP_TRANSIT_S


def jog_reach_s(limits: ArmLimits, backstop_s: float = 0.0) -> float:
    """How long one jog can move the TCP at its speed, at most, if no other command comes.

    Its lifetime (``jog_timeout_s``); then whichever stop comes last: the
    deadman's (its wake period and the stop's transit) or, where the deadman
    itself was starved, the controller's (``backstop_s`` after the deadline:
    ``Arm.jog_backstop_s``, 0 for an arm whose controller watches nothing);
    and the deceleration from the speed cap (v / 2a per unit of v).
    """
    decel = limits.max_linear_speed_m_s / (2.0 * limits.stop_deceleration_m_s2)
    return limits.jog_timeout_s + max(jog_overdue_s(limits), backstop_s) + decel


def clip_jog_velocity(
    limits: ArmLimits,
    velocity: Sequence[float],
    pose: Sequence[float] | None = None,
    backstop_s: float = 0.0,
) -> np.ndarray:
    """The velocity a jog actually sends: speed-capped, and kept inside the box.

    Linear and angular parts are scaled (direction kept) to their caps. A
    linear component that points toward a face is slowed so that the jog
    cannot carry the TCP past it before the deadman, or the controller's
    watchdog ``backstop_s`` after its deadline, has stopped it (``jog_reach_s``):
    the box holds even if no fresher jog comes, from a starved node or a
    wedged link, and for an arm with a watchdog even if the deadman starved.
    At or beyond the face it is zero, so the operator can always jog back in.
    A function of the limits (and the arm's backstop) alone, so an exporter
    can apply it to recorded commands.
    """
    v = as_vector6(velocity, "jog velocity")
    lin, ang = v[:3], v[3:]
    n = float(np.linalg.norm(lin))
    if n > limits.max_linear_speed_m_s:
        lin = lin * (limits.max_linear_speed_m_s / n)
    n = float(np.linalg.norm(ang))
    if n > limits.max_angular_speed_rad_s:
        ang = ang * (limits.max_angular_speed_rad_s / n)
    lin = lin.copy()
    if pose is not None:
        xyz = as_vector6(pose, "pose")[:3]
        life = jog_reach_s(limits, backstop_s)
        for i in range(3):
            if lin[i] > 0:
                lin[i] = min(lin[i], max(0.0, limits.workspace_max[i] - xyz[i]) / life)
            elif lin[i] < 0:
                lin[i] = max(lin[i], -max(0.0, xyz[i] - limits.workspace_min[i]) / life)
    return np.concatenate([lin, ang])
