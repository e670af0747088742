"""What every server of the simulated controller shares: its settings, its lock and the arm.

The RTDE server, the dashboard and the control script all act on one
controller: a kinematic UR3e (:class:`~robot_side.arm.sim.kinematics.KinematicArm`),
its safety mode and power, and the controller's clock, all under one lock.
"""

from __future__ import annotations

import math
import threading
from collections import deque
from dataclasses import dataclass

import numpy as np

from common.clocks.clock import now_s
from common.config.typed import param
from common.errors import ConfigError
from robot_side.arm.sim.kinematics import HOME_Q, KinematicArm, Mode

RTDE_PORT = 30004
DASHBOARD_PORT = 29999
SCRIPT_PORT = 30003

#: what may move the arm (``URSimConfig.motion_clock``)
MOTION_CLOCKS = ("wall", "external")

ROBOT_MODE_RUNNING = 7
SAFETY_MODE_NORMAL = 1
SAFETY_MODE_PROTECTIVE_STOP = 3

#: how long the simulator keeps the TCP's speed at each step (Controller.at_rest_since)
MOTION_LOG_S = 10.0


@dataclass
class URSimConfig:
    host: str = param(
        "auto", "loopback address to serve on; 'auto' takes a free 127.0.0.x (ports are fixed)"
    )
    tick_hz: float = param(500.0, "controller cycle: the e-Series runs at 500 Hz")
    controller_version: tuple[int, int, int, int] = param(
        (5, 11, 6, 1088), "what GET_URCONTROL_VERSION answers; major > 3 means e-Series"
    )
    polyscope_version: str = param("URSoftware 5.11.6.1088 (Jun 03 2022)", "dashboard reply")
    serial_number: str = param(
        "20205500042", "dashboard 'get serial number' (ur-rtde wants digits)"
    )
    tcp_offset: tuple[float, float, float, float, float, float] = param(
        (0.0, 0.0, 0.15, 0.0, 0.0, 0.0), "TCP in the flange frame: the 2F-85 fingertip centre"
    )
    home_q: tuple[float, float, float, float, float, float] = param(
        HOME_Q, "joint angles at power-on (rad): tool down above the table"
    )
    script_start_delay_s: float = param(0.02, "time from script upload to 'program running'")
    program_stop_deceleration_m_s2: float = param(
        10.0,
        "how hard the arm stops when the program ends (stopScript, the dashboard's stop, the "
        "RTDE watchdog, a runtime error); ur-rtde's own stop default, not a measured UR figure",
    )
    motion_clock: str = param(
        "wall",
        "what moves the arm: 'wall' (the controller's own cycle, real time) or 'external' "
        "(only advance(dt) does: a physics world's simulated time, so a world that falls "
        "behind slows the arm alike; the RTDE watchdog counts that time too, the wire and "
        "the script's handshake stay on real time)",
    )


class Controller:
    """The controller's state under ``lock``: the arm, safety mode, power and clock."""

    #: SCHED_FIFO priority of the threads of a process that serves it, where granted (the
    #: process raises its first thread before it starts the others: they inherit it): a
    #: controller is hard real time and never waits for the PC's CPU. Below the arm process's
    #: (19, its keep-alive 20), as the real one is a machine of its own. At the robot node's
    #: niceness the simulator, starved beside a loaded test lane, stopped streaming for 200 ms
    #: and held a client's stop handshake. A numpy pool thread made before the raise stays
    #: fair (its spin while it waits would hold a core; ``URSimProcess`` starts none).
    REALTIME_PRIORITY = 10

    def __init__(self, config: URSimConfig | None = None) -> None:
        self.config = config or URSimConfig()
        if self.config.tick_hz <= 0:
            raise ConfigError("URSimConfig.tick_hz must be positive")
        if self.config.motion_clock not in MOTION_CLOCKS:
            raise ConfigError(
                f"URSimConfig.motion_clock must be one of {MOTION_CLOCKS}, "
                f"not {self.config.motion_clock!r}"
            )
        self.lock = threading.RLock()
        self.arm = self._home_arm()
        self.safety_mode = SAFETY_MODE_NORMAL
        self.powered = True
        self._t0 = now_s()
        #: the controller's clock in motion_clock "wall": the time the arm was stepped by, so
        #: a tick the machine stalled costs the clock what it costs the motion (a real
        #: controller is hard real time: its timestamps and motion always agree)
        self.clock_s = 0.0
        #: (when, linear m/s, angular rad/s) after each step of the last MOTION_LOG_S: when the
        #: arm came to rest, on the clock every process shares, for an observer that may have
        #: looked late
        self._motion_log: deque[tuple[float, float, float]] = deque(
            maxlen=max(1, math.ceil(MOTION_LOG_S * self.config.tick_hz))
        )

    def _home_arm(self) -> KinematicArm:
        return KinematicArm(
            tcp_offset=np.array(self.config.tcp_offset, dtype=float),
            q=np.array(self.config.home_q, dtype=float),
        )

    def timestamp(self) -> float:
        """The RTDE ``timestamp``: the controller's clock (``clock_s``), or the time since it
        started when an owner moves the arm (motion_clock "external")."""
        return self.clock_s if self.config.motion_clock == "wall" else now_s() - self._t0

    def note_motion(self) -> None:
        """Record the TCP's speed after a step (``at_rest_since``); call with ``lock`` held."""
        v = self.arm.velocity.tolist()
        self._motion_log.append((now_s(), math.hypot(*v[:3]), math.hypot(*v[3:])))

    def teleport_home(self) -> None:
        """The arm back at its home joints, at rest: a fresh trial (simulation only)."""
        with self.lock:
            self.arm = self._home_arm()
            self.safety_mode = SAFETY_MODE_NORMAL

    def unlock_protective_stop(self) -> None:
        with self.lock:
            self.safety_mode = SAFETY_MODE_NORMAL

    # -- state seen by tests -------------------------------------------------

    def tcp_pose(self) -> np.ndarray:
        with self.lock:
            return self.arm.current_pose()

    def joint_positions(self) -> np.ndarray:
        """The joints as the controller has them: what a physics world shows and checks."""
        with self.lock:
            return self.arm.q.copy()

    def tcp_speed(self) -> np.ndarray:
        with self.lock:
            return self.arm.velocity.copy()

    @property
    def mode(self) -> Mode:
        return self.arm.mode

    def mode_name(self) -> str:
        """What the arm is doing: idle, moveL, moveJ, speedL, servoL or stopping."""
        return self.arm.mode.value

    def at_rest_since(self, linear_m_s: float, angular_rad_s: float) -> float | None:
        """Since when (``time.monotonic()``, which every process on this machine shares) the
        TCP has moved no faster than both limits at every step; None while it moves faster.

        The controller's own record: a test that looks late (its process starved) still
        reads when the arm stopped, not when it looked. Kept for the last MOTION_LOG_S.
        """
        with self.lock:
            since = None
            for t, linear, angular in reversed(self._motion_log):
                if linear > linear_m_s or angular > angular_rad_s:
                    break
                since = t
            return since
