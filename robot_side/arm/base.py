"""The arm interface: read the TCP, jog it, move it, stop it, within limits.

Poses are ``[x, y, z, rx, ry, rz]`` in the robot base frame: metres and a
rotation vector in radians (UR's convention). Velocities are
``[vx, vy, vz, wx, wy, wz]`` in m/s and rad/s.

Safety lives here, not in the drivers: a jog is clipped to the speed limits
and loses any component that would leave the workspace box; a ``move_to``
outside the box is refused; a jog lasts only ``jog_timeout_s`` from when it
was issued unless the operator sends another (the deadman), so a lost link
stops the arm; every stop decelerates at ``stop_deceleration_m_s2``. The
limits and the clipping are in ``limits``, the deadman and keep-alive
threads in ``safety_threads``.
"""

from __future__ import annotations

import abc
import logging
import math
import threading
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from common.clocks.clock import now_s
from common.devices.lifecycle import Device
from common.errors import DeviceError, DeviceTimeoutError
from robot_side.arm.limits import (
    STOP_TRANSIT_S,
    ArmLimits,
    WorkspaceLimitError,
    as_vector6,
    clip_jog_velocity,
    deadman_period_s,
    jog_overdue_s,
    jog_reach_s,
    turn_angle,
)
from robot_side.arm.safety_threads import (
    NATIVE_DRIVER_THREAD_NICE,
    SAFETY_THREAD_NICE,
    SafetyThreads,
)

__all__ = [
    "NATIVE_DRIVER_THREAD_NICE",
    "SAFETY_THREAD_NICE",
    "STOP_TRANSIT_S",
    "TELEMETRY_POSE_KEYS",
    "Arm",
    "ArmLimits",
    "WorkspaceLimitError",
    "as_vector6",
    "clip_jog_velocity",
    "deadman_period_s",
    "jog_overdue_s",
    "jog_reach_s",
    "turn_angle",
]

log = logging.getLogger(__name__)


#: Heartbeat stats keys of the TCP pose (metres, rotation vector in radians).
TELEMETRY_POSE_KEYS = ("arm_x", "arm_y", "arm_z", "arm_rx", "arm_ry", "arm_rz")


class Arm(SafetyThreads, Device):
    """A 6-DoF arm with a TCP: reads, clipped jogs with a deadman, checked moves, stop.

    Drivers implement ``_read_tcp_pose``, ``_read_joints``, ``_send_jog``,
    ``_send_move``, ``_move_finished`` and ``_send_stop``; they call ``_start_deadman()`` at the
    end of ``connect`` and ``_stop_deadman()`` at the start of ``disconnect``.
    Calls into the driver are serialised by ``_lock`` so the deadman thread
    and the caller never interleave on the wire.
    """

    family = "arm"

    def __init__(self, limits: ArmLimits | None = None) -> None:
        self.limits = limits or ArmLimits()
        self._lock = threading.RLock()
        self._jog_until: float | None = None  # monotonic s; None when not jogging
        self._last_jog = np.zeros(6)
        self._init_safety_threads()

    # -- what drivers implement -------------------------------------------

    @abc.abstractmethod
    def _read_tcp_pose(self) -> np.ndarray: ...

    @abc.abstractmethod
    def _read_joints(self) -> np.ndarray: ...

    @abc.abstractmethod
    def _send_jog(self, velocity: np.ndarray) -> None:
        """Command a TCP velocity (already clipped)."""

    @abc.abstractmethod
    def _send_move(self, pose: np.ndarray, speed: float) -> None:
        """Start a linear move to ``pose`` (already checked); must not wait for it."""

    @abc.abstractmethod
    def _move_finished(self) -> bool:
        """True once the last move has ended (reached, stopped or aborted)."""

    @abc.abstractmethod
    def _send_stop(self) -> None:
        """Decelerate to standstill; must not raise when already stopped."""

    # -- public API --------------------------------------------------------

    def tcp_pose(self) -> np.ndarray:
        self.require_connected()
        return self._read_tcp_pose()

    def joint_positions(self) -> np.ndarray:
        self.require_connected()
        return self._read_joints()

    def clip_jog(
        self, velocity: Sequence[float], pose: Sequence[float] | None = None
    ) -> np.ndarray:
        """The velocity a jog actually sends (``clip_jog_velocity`` with these limits)."""
        return clip_jog_velocity(self.limits, velocity, pose, self.jog_backstop_s)

    @property
    def jog_backstop_s(self) -> float:
        """How long after a jog's deadline the controller itself stops the arm when the
        deadman could not (it starved): 0 for an arm whose controller watches nothing, so
        its jogs reach only as far as the deadman stops them. ``URArm``: the overdue grace
        plus the watchdog's window (the keep-alive stops kicking for an overdue jog)."""
        return 0.0

    def jog(self, velocity: Sequence[float], issued_at_s: float | None = None) -> np.ndarray:
        """Move the TCP at ``velocity`` until the next jog, ``stop()`` or the deadman.

        The deadman stops the arm ``limits.jog_timeout_s`` after the jog was
        issued (``issued_at_s``, monotonic seconds on this machine: when the
        operator sent it; default now): an operator holding a jog key must
        keep sending it, and a jog that arrives late moves the arm only for
        what is left of its time. Returns the velocity actually sent (zeros:
        the arm was stopped instead).
        """
        self.require_connected()
        now = now_s()
        until = now + self.limits.jog_timeout_s
        if issued_at_s is not None:
            until = min(until, issued_at_s + self.limits.jog_timeout_s)
        with self._lock:
            v = self.clip_jog(velocity, self._read_tcp_pose())
            if until <= now or not np.any(v):
                self._stop_locked()
                return np.zeros(6)
            self._send_jog(v)
            self._last_jog = v
            self._jog_until = until
            return v

    def move_to(self, pose: Sequence[float], speed: float | None = None, wait: bool = True) -> None:
        """Move the TCP linearly to ``pose``; refuses targets outside the workspace box.

        With ``wait`` the call returns when the move has ended; ``stop()`` from
        another thread ends it early. Speeds above the limit are clipped.
        """
        self.require_connected()
        target = as_vector6(pose, "target pose")
        if not self.limits.contains(target[:3]):
            raise WorkspaceLimitError(
                f"target {np.round(target[:3], 4).tolist()} m is outside the workspace box "
                f"{list(self.limits.workspace_min)}..{list(self.limits.workspace_max)}; "
                "choose a target inside it or widen [arm.limits] if the cell allows"
            )
        if speed is None:
            speed = self.limits.default_move_speed_m_s
        if not (isinstance(speed, (int, float)) and math.isfinite(speed) and speed > 0):
            raise ValueError(f"move speed must be a positive number, not {speed!r}")
        if speed > self.limits.max_linear_speed_m_s:
            log.warning(
                "move speed %.3f m/s clipped to %.3f", speed, self.limits.max_linear_speed_m_s
            )
            speed = self.limits.max_linear_speed_m_s
        with self._lock:
            self._jog_until = None
            start = self._read_tcp_pose()
            self._send_move(target, float(speed))
        if wait:
            # a pure turn's moveL runs at ``speed`` rad/s: its length is the angle
            distance = max(
                float(np.linalg.norm(target[:3] - start[:3])),
                turn_angle(start[3:], target[3:]),
            )
            accel = self.limits.linear_acceleration_m_s2
            # twice the trapezoid's duration, plus slack for the handshake and rotations
            timeout = 2 * (distance / speed + speed / accel) + 5.0
            self._wait_move(timeout)

    def move_finished(self) -> bool:
        """True once the last move has ended (reached, stopped or aborted)."""
        self.require_connected()
        with self._lock:
            return bool(self._move_finished())

    def _wait_move(self, timeout_s: float) -> None:
        """Poll for the end of a move without holding the lock, so ``stop()`` can cut in."""
        deadline = now_s() + timeout_s
        while True:
            with self._lock:
                if self._move_finished():
                    return
            if now_s() > deadline:
                self.stop()
                raise DeviceTimeoutError(
                    f"{type(self).__name__}: move did not finish in {timeout_s:.1f} s; "
                    "the arm was told to stop. Check the pendant for a protective stop."
                )
            time.sleep(0.01)

    def stop(self) -> None:
        """Stop any motion. Safe to call at any time, also when not connected."""
        if not self.is_connected:
            return
        with self._lock:
            self._stop_locked()

    def _stop_locked(self) -> None:
        self._jog_until = None
        self._last_jog = np.zeros(6)
        self._send_stop()

    def status(self) -> dict[str, Any]:
        out = super().status()
        out.update(jogging=self._jog_until is not None, deadman_stops=self._deadman_stops)
        if self.is_connected:
            try:
                out["tcp_pose"] = np.round(self.tcp_pose(), 5).tolist()
                out["joints"] = np.round(self.joint_positions(), 5).tolist()
            except DeviceError as e:
                out["error"] = str(e)
        return out

    def live_readings(self) -> dict[str, float]:
        """The newest pose (and what else the driver streams) without a device call.

        For the robot's heartbeat, which must not wait for the arm's worker
        (busy for a whole stop): values another thread already received,
        under ``TELEMETRY_POSE_KEYS`` and the ``telemetry()`` names. Empty
        when the driver has no such stream or it is not live. Never blocks.
        """
        return {}

    def telemetry(self) -> dict[str, float]:
        """What the operator's dashboard shows, as flat numbers for the heartbeat's stats.

        The TCP pose, whether a jog is live and how often the deadman stopped
        one, and the safety envelope (workspace box, speed caps) so the
        operator draws the box the robot actually enforces. Drivers add what
        their controller reports (speed, safety mode, program state).
        """
        out = {**self.driver_state(), **self.keep_alive_telemetry(), **self.envelope()}
        if self.is_connected:
            pose = self._read_tcp_pose()
            out.update(zip(TELEMETRY_POSE_KEYS, (float(v) for v in pose), strict=True))
        return out

    def driver_state(self) -> dict[str, float]:
        """Of the telemetry, what only the driver knows: whether a jog is live and how often
        the deadman stopped one; drivers add their controller's state (safety mode, program).
        Raises where ``telemetry`` does: the arm process writes this for the node's poll at
        the heartbeat's rate, without the rest (the pose it writes anyway; the envelope and
        the keep-alive's timing the node has)."""
        return {
            "arm_jogging": float(self._jog_until is not None),
            "arm_deadman_stops": float(self._deadman_stops),
        }

    def envelope(self) -> dict[str, float]:
        """The safety envelope the arm enforces (speed caps, workspace box), as flat numbers."""
        lim = self.limits
        out = {
            "arm_max_linear_m_s": lim.max_linear_speed_m_s,
            "arm_max_angular_rad_s": lim.max_angular_speed_rad_s,
        }
        for axis, lo, hi in zip("xyz", lim.workspace_min, lim.workspace_max, strict=True):
            out[f"arm_ws_min_{axis}"] = float(lo)
            out[f"arm_ws_max_{axis}"] = float(hi)
        return out
