"""The controller's state stream (RTDEReceiveInterface): reads that refuse to be old.

ur-rtde's receive getters keep returning their last cache once the controller
is gone, so every read here checks ``isConnected()`` and that the
controller's timestamp still advances, and raises instead of handing out an
old pose.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from common.clocks.clock import now_s
from common.errors import DeviceError, DeviceNotConnectedError, StaleDataError
from common.wire.messages import ARM_SAFETY_MODES
from robot_side.arm.base import TELEMETRY_POSE_KEYS
from robot_side.arm.ur_rtde.config import URArmConfig

#: the TCP counts as at rest below these speeds (m/s, rad/s)
AT_REST_M_S = 1e-4
AT_REST_RAD_S = 1e-3


def at_rest(speed: np.ndarray) -> bool:
    """A TCP speed ``[vx, vy, vz, wx, wy, wz]`` that counts as standing still."""
    return bool(
        np.linalg.norm(speed[:3]) <= AT_REST_M_S and np.linalg.norm(speed[3:]) <= AT_REST_RAD_S
    )


class ReceiveSide:
    """The receive interface while connected (``recv``), and how fresh its data is."""

    def __init__(self, config: URArmConfig) -> None:
        self.config = config
        self.recv: Any = None
        #: reads refused because the controller's timestamp stood still too long
        self.stale_events = 0
        self._last_ts = -1.0
        self._last_ts_change = 0.0
        self._live_ts, self._live_ts_change = -1.0, 0.0  # live_readings' own view of the stream

    def open(self, recv: Any) -> None:
        self.recv = recv
        self._last_ts = recv.getTimestamp()
        self._last_ts_change = now_s()

    def close(self) -> Any:
        """No interface from here on; the one that was, for the caller to close."""
        recv, self.recv = self.recv, None
        return recv

    def fresh(self) -> Any:
        """The receive interface, after checking that its cache is live."""
        recv = self.recv
        if recv is None:
            raise DeviceNotConnectedError("arm URArm is not connected: call connect() first")
        if not recv.isConnected():
            raise DeviceNotConnectedError(
                f"URArm: lost the RTDE connection to {self.config.host}; the values ur-rtde "
                "still returns are its last cache. Check the controller, then disconnect() "
                "and connect() again"
            )
        ts = recv.getTimestamp()
        now = now_s()
        if ts != self._last_ts:
            self._last_ts, self._last_ts_change = ts, now
        elif now - self._last_ts_change > self.config.stale_after_s:
            self.stale_events += 1
            raise StaleDataError(
                f"URArm: the controller timestamp has not advanced for "
                f"{(now - self._last_ts_change) * 1000:.0f} ms (limit "
                f"{self.config.stale_after_s * 1000:.0f} ms): it stopped streaming. "
                "Check the controller; reconnect if it does not recover"
            )
        return recv

    def data_age_s(self) -> float:
        """How long ago the controller's timestamp last advanced, as the reads saw it."""
        return now_s() - self._last_ts_change

    def live_readings(self) -> dict[str, float]:
        """The receive interface's newest TCP pose and speed, read from its cache.

        ur-rtde's receive thread fills that cache from its own connection, so
        this never waits for the control side (a stop, a move's handshake) or
        the driver's lock; the getters take microseconds. Nothing when the
        stream is lost or stale (``stale_after_s``, judged on this caller's own
        reads).
        """
        recv = self.recv
        if recv is None:
            return {}
        try:
            if not recv.isConnected():
                return {}
            ts, now = float(recv.getTimestamp()), now_s()
            if ts != self._live_ts:
                self._live_ts, self._live_ts_change = ts, now
            elif now - self._live_ts_change > self.config.stale_after_s:
                return {}
            pose = recv.getActualTCPPose()
            speed = np.asarray(recv.getActualTCPSpeed(), dtype=float)
        except RuntimeError:  # the interface closed under us (a reconnect): nothing live
            return {}
        out = dict(zip(TELEMETRY_POSE_KEYS, (float(v) for v in pose), strict=True))
        out["arm_speed_m_s"] = float(np.linalg.norm(speed[:3]))
        out["arm_angular_speed_rad_s"] = float(np.linalg.norm(speed[3:]))
        return out

    def tcp_pose(self) -> np.ndarray:
        return np.asarray(self.fresh().getActualTCPPose(), dtype=float)

    def joints(self) -> np.ndarray:
        return np.asarray(self.fresh().getActualQ(), dtype=float)

    def tcp_speed(self) -> np.ndarray:
        return np.asarray(self.fresh().getActualTCPSpeed(), dtype=float)

    def controller_timestamp(self) -> float:
        """Seconds since the controller booted, as the last data package said."""
        return float(self.fresh().getTimestamp())

    def last_timestamp(self) -> float | None:
        """The newest package's controller time, however old (None: none can be read)."""
        recv = self.recv
        if recv is None:
            return None
        try:
            return float(recv.getTimestamp())
        except RuntimeError:  # the interface closed under us
            return None

    def seen_at_rest(self) -> bool:
        """The stream shows the TCP still (False when it cannot be read)."""
        try:
            speed = self.tcp_speed()
        except (DeviceError, RuntimeError):
            return False
        return at_rest(speed)

    def safety_text(self) -> str:
        """The safety mode's name, for an error message ("unknown" when it cannot be read)."""
        try:
            mode = int(self.recv.getSafetyMode())
        except Exception:  # only used to word an error message
            return "unknown"
        return ARM_SAFETY_MODES.get(mode, f"mode {mode}")
