"""The arm interface: read the TCP, jog it, move it, stop it, within limits.

Poses are ``[x, y, z, rx, ry, rz]`` in the robot base frame: metres and a
rotation vector in radians (UR's convention). Velocities are
``[vx, vy, vz, wx, wy, wz]`` in m/s and rad/s.

Safety lives here, not in the drivers: a jog is clipped to the speed limits
and loses any component that would leave the workspace box; a ``move_to``
outside the box is refused; a jog lasts only ``jog_timeout_s`` from when it
was issued unless the operator sends another (the deadman), so a lost link
stops the arm; every stop decelerates at ``stop_deceleration_m_s2``.
"""

from __future__ import annotations

import abc
import logging
import math
import os
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from common.clock import now_s
from common.config import param
from common.devices import Device, at_niceness
from common.errors import ConfigError, DeviceError, DeviceTimeoutError
from common.realtime import PeriodStats, Scheduling, raise_this_thread
from common.rotation import rotation_angle, rotvec_to_matrix

log = logging.getLogger(__name__)


#: Heartbeat stats keys of the TCP pose (metres, rotation vector in radians).
TELEMETRY_POSE_KEYS = ("arm_x", "arm_y", "arm_z", "arm_rx", "arm_ry", "arm_rz")


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

#: The deadman's, the keep-alive's and a driver's control threads run above the rest of
#: the robot node (its unit's Nice=-10) where the process may raise them (the unit's
#: LimitNICE=-15), like ur-rtde's own ``rt_priority``. They sleep between short turns, so
#: they take little; what they need is the CPU when they wake. At the node's own priority
#: they queued behind ur-rtde's two receive threads (which poll every 100 us), the other
#: threads of the node and whatever else runs at -10: on a saturated 2-core machine the
#: keep-alive waited 168 ms for a CPU within 0.4 s (its schedstat) and the controller's
#: watchdog tripped. A driver used from a process at ordinary priority (a tool, a test, a
#: notebook) still stops its jogs and kicks its controller's watchdog. Their priority does
#: not help while a preempted thread of the node holds the interpreter lock they each need,
#: and the whole node at -15 starved the simulated hardware instead (docs/robustness.md).
SAFETY_THREAD_NICE = -15
#: ur-rtde's own threads (the receive loops that poll every 100 us) run at the robot unit's
#: Nice=-10 whichever thread connects (a reconnect may come from a -15 thread): they never
#: take the interpreter lock, and at -15 their polling would stand in front of the safety
#: threads. A driver in a process at lower priority leaves them at its own.
NATIVE_DRIVER_THREAD_NICE = -10


def deadman_period_s(limits: ArmLimits) -> float:
    """How often the deadman thread wakes: its jog check and ``_keep_alive`` run this often."""
    return min(0.02, limits.jog_timeout_s / 5)


def jog_reach_s(limits: ArmLimits) -> float:
    """How long one jog can move the TCP at its speed, at most, if no other command comes.

    Its lifetime (``jog_timeout_s``), the deadman's wake period, the stop's
    transit, and its deceleration from the speed cap (v / 2a per unit of v).
    """
    decel = limits.max_linear_speed_m_s / (2.0 * limits.stop_deceleration_m_s2)
    return limits.jog_timeout_s + deadman_period_s(limits) + STOP_TRANSIT_S + decel


def clip_jog_velocity(
    limits: ArmLimits, velocity: Sequence[float], pose: Sequence[float] | None = None
) -> np.ndarray:
    """The velocity a jog actually sends: speed-capped, and kept inside the box.

    Linear and angular parts are scaled (direction kept) to their caps. A
    linear component that points toward a face is slowed so that the jog
    cannot carry the TCP past it before the deadman has stopped it
    (``jog_reach_s``): the box holds even if no fresher jog comes, from a
    starved node or a wedged link. At or beyond the face it is zero, so the
    operator can always jog back in. A function of the limits alone, so an
    exporter can apply it to recorded commands.
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
        life = jog_reach_s(limits)
        for i in range(3):
            if lin[i] > 0:
                lin[i] = min(lin[i], max(0.0, limits.workspace_max[i] - xyz[i]) / life)
            elif lin[i] < 0:
                lin[i] = max(lin[i], -max(0.0, xyz[i] - limits.workspace_min[i]) / life)
    return np.concatenate([lin, ang])


class Arm(Device):
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
        self._deadman_stops = 0
        self._deadman_thread: threading.Thread | None = None
        self._keep_alive_thread: threading.Thread | None = None
        self._deadman_quit = threading.Event()
        self._deadman_woke = 0.0  # monotonic s: the deadman thread's latest wake
        self._deadman_stopping_since: float | None = None  # it waits for a stop since then
        #: SCHED_FIFO priority of the deadman and keep-alive threads (None: a niceness only);
        #: the arm's own process sets it (robot_side/arm/process)
        self.realtime_priority: int | None = None
        #: what the keep-alive thread got from the scheduler, once it runs
        self.keep_alive_scheduling: Scheduling | None = None
        #: the intervals between the keep-alive thread's wakes (nominal: the deadman period)
        self.keep_alive_periods = PeriodStats(deadman_period_s(self.limits))

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
        return clip_jog_velocity(self.limits, velocity, pose)

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
        lim = self.limits
        out = {
            "arm_jogging": float(self._jog_until is not None),
            "arm_deadman_stops": float(self._deadman_stops),
            **self.keep_alive_telemetry(),
            "arm_max_linear_m_s": lim.max_linear_speed_m_s,
            "arm_max_angular_rad_s": lim.max_angular_speed_rad_s,
        }
        for axis, lo, hi in zip("xyz", lim.workspace_min, lim.workspace_max, strict=True):
            out[f"arm_ws_min_{axis}"] = float(lo)
            out[f"arm_ws_max_{axis}"] = float(hi)
        if self.is_connected:
            pose = self._read_tcp_pose()
            out.update(zip(TELEMETRY_POSE_KEYS, (float(v) for v in pose), strict=True))
        return out

    def keep_alive_summary(self) -> dict[str, float]:
        """The keep-alive's period (p50, p99, p999, max in ms, count) and whether it runs
        real-time (``realtime`` 1/0, ``level``: its priority or niceness); {} before it ran."""
        summary = self.keep_alive_periods.summary()
        if not summary:
            return {}
        got = self.keep_alive_scheduling
        summary.pop("nominal_ms", None)
        if got is not None:
            summary.update(realtime=float(got.realtime), level=float(got.level))
        return summary

    def keep_alive_telemetry(self) -> dict[str, float]:
        """How on time the keep-alive runs: its period's p99 and max (ms), and whether it runs
        real-time (1) or at a niceness (0); nothing for a driver without a keep-alive."""
        summary = self.keep_alive_periods.summary()
        if not summary:
            return {}
        got = self.keep_alive_scheduling
        return {
            "arm_keepalive_p99_ms": summary["p99_ms"],
            "arm_keepalive_max_ms": summary["max_ms"],
            "arm_keepalive_realtime": float(got is not None and got.realtime),
        }

    # -- deadman -----------------------------------------------------------

    def _start_deadman(self) -> None:
        """The deadman thread and, for a driver with a ``_keep_alive``, the thread that kicks."""
        self._deadman_quit.clear()
        self._jog_until = None
        self._deadman_woke = now_s()
        self.keep_alive_periods.clear()  # a new connection: a new series
        name = type(self).__name__
        t = threading.Thread(target=self._safety_thread(self._deadman_loop), name=f"{name}-deadman")
        t.daemon = True
        self._deadman_thread = t
        t.start()
        if type(self)._keep_alive is not Arm._keep_alive:
            k = threading.Thread(
                target=self._safety_thread(self._keep_alive_loop, note=True),
                name=f"{name}-keepalive",
            )
            k.daemon = True
            self._keep_alive_thread = k
            k.start()

    def _safety_thread(self, loop: Callable[[], None], note: bool = False) -> Callable[[], None]:
        """``loop`` at SCHED_FIFO ``realtime_priority`` where set and granted, else at the
        safety threads' niceness; ``note``: the keep-alive records what it got."""
        priority = self.realtime_priority
        if priority is None:

            def noted() -> None:
                if note:  # in the node (own_process = false): the niceness it got
                    tid = threading.get_native_id()
                    self.keep_alive_scheduling = Scheduling(
                        "nice", os.getpriority(os.PRIO_PROCESS, tid)
                    )
                loop()

            return at_niceness(SAFETY_THREAD_NICE, noted)

        def run() -> None:
            got = raise_this_thread(priority, SAFETY_THREAD_NICE)
            if note:
                self.keep_alive_scheduling = got
                log.info("%s keep-alive at %s", type(self).__name__, got.describe())
            loop()

        return run

    def _stop_deadman(self) -> None:
        self._deadman_quit.set()
        threads = (self._deadman_thread, self._keep_alive_thread)
        self._deadman_thread = self._keep_alive_thread = None
        for t in threads:
            if t is not None and t is not threading.current_thread():
                t.join(timeout=2.0)

    @property
    def deadman_responsive(self) -> bool:
        """The deadman thread woke within a jog's lifetime (``jog_timeout_s``), or is making
        a stop that has not yet outlasted ``_deadman_stop_limit_s``.

        Stuck longer, it could not stop a jog either, and a keep-alive must
        then let the controller's own watchdog stop the arm.
        """
        now = now_s()
        if now - self._deadman_woke <= self.limits.jog_timeout_s:
            return True
        since = self._deadman_stopping_since
        return since is not None and now - since <= self._deadman_stop_limit_s()

    def _deadman_stop_limit_s(self) -> float:
        """The longest a stop (the lock's wait included) may take before the deadman counts as
        stuck; drivers whose calls have deadlines say theirs."""
        return 2.0

    @property
    def deadman_period_s(self) -> float:
        """How often the deadman thread wakes: its jog check and ``_keep_alive`` run this often."""
        return deadman_period_s(self.limits)

    def _keep_alive(self) -> None:
        """Tell the controller this process is alive; called every deadman period.

        Runs on a thread of its own, which lives and dies (or freezes) with
        this process, so a controller that watches for it stops the arm when
        the process cannot (ur-rtde's watchdog, ``URArm``). Not the deadman
        thread: that one makes the deadman's stops, and a stop may wait for
        the whole deceleration. It must never block. Nothing to do by default
        (and then no thread runs).
        """

    def _keep_alive_loop(self) -> None:
        """Every deadman period on absolute deadlines (a late turn does not push the next
        back); each wake is noted in ``keep_alive_periods``."""
        period = self.deadman_period_s
        due = now_s() + period
        while not self._deadman_quit.wait(max(0.0, due - now_s())):
            now = now_s()
            self.keep_alive_periods.woke(now)
            due += period
            if due < now:  # more than a period late: start again from now, no burst of turns
                due = now + period
            try:
                self._keep_alive()
            except Exception:  # the next period tries again
                log.exception("%s: keep-alive failed", type(self).__name__)

    def _deadman_loop(self) -> None:
        period = self.deadman_period_s
        while not self._deadman_quit.wait(period):
            self._deadman_woke = now_s()
            until = self._jog_until
            if until is None or now_s() < until:
                continue
            self._deadman_stopping_since = now_s()
            try:
                self._deadman_stop()
            finally:
                self._deadman_stopping_since = None

    def _deadman_stop(self) -> None:
        with self._lock:
            if self._jog_until is None or now_s() < self._jog_until:
                return  # a jog or stop arrived meanwhile
            log.warning("no jog for %.2f s: stopping the arm (deadman)", self.limits.jog_timeout_s)
            self._deadman_stops += 1
            try:
                self._stop_locked()
            except Exception:  # the thread must survive to try again
                log.exception("deadman stop failed")
                self._jog_until = now_s() + self.limits.jog_timeout_s
