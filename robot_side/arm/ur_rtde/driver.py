"""``URArm``: the arm interface on a UR controller, made of the parts this package holds.

Connect opens both interfaces (``connection``), starts the deadman and
keep-alive threads and arms the controller's watchdog (``keep_alive``);
reads go to the receive side (``receive``), jogs, moves and stops to the
motion (``motion``) on the control line (``control``). Disconnect stops the
arm, ends the control script and closes both interfaces, whatever fails.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from common.devices.preflight import Finding, PreflightContext, tcp_findings
from common.errors import DeviceAlreadyConnectedError, DeviceError
from robot_side.arm.base import Arm, jog_overdue_s
from robot_side.arm.ur_rtde.config import URArmConfig, check_watchdog_config
from robot_side.arm.ur_rtde.connection import CONTROLLER_PORTS, close_interfaces, open_interfaces
from robot_side.arm.ur_rtde.control import ControlLine
from robot_side.arm.ur_rtde.control_receiver import ControlReceiver
from robot_side.arm.ur_rtde.keep_alive import (
    WATCHDOG_ARM_TRIES,
    ControllerWatchdog,
    WatchdogArmingLostError,
)
from robot_side.arm.ur_rtde.motion import Motion
from robot_side.arm.ur_rtde.receive import ReceiveSide

log = logging.getLogger(__name__)


class URArm(Arm):
    """A UR e-Series arm through ur-rtde.

    Its parts, for callers that need one: ``receive`` (the state stream and
    its reads), ``line`` (the control connection and the script behind it),
    ``watchdog`` (the controller's watchdog and its kicks) and ``motion``
    (what is moving and how it stops).
    """

    Config = URArmConfig

    def __init__(self, config: URArmConfig | None = None) -> None:
        self.config = config or URArmConfig()
        super().__init__(self.config.limits)
        check_watchdog_config(self.config, self.limits, self.deadman_period_s)
        self.receive = ReceiveSide(self.config)
        self.line = ControlLine(self.config, self.receive)
        self.watchdog = ControllerWatchdog(
            self.config, self.limits, self.receive, self.line, lambda: self.deadman_responsive
        )
        self.motion = Motion(self.config, self.limits, self.receive, self.line, self.watchdog)

    @property
    def jog_backstop_s(self) -> float:
        """An overdue jog gets no more kicks, and the controller stops the arm a watchdog
        window after the last one: the box holds even while this process starves."""
        return jog_overdue_s(self.limits) + self.config.watchdog_window_s

    # -- lifecycle -----------------------------------------------------------

    def _preflight(self, context: PreflightContext) -> list[Finding]:
        hint = (
            "on the pendant: robot powered on, Remote Control mode "
            "(Settings > System > Remote Control), no firewall on the controller"
        )
        return tcp_findings(self.config.host, CONTROLLER_PORTS, context, hint)

    def _location(self) -> str:
        return f"at {self.config.host} ports {sorted(CONTROLLER_PORTS)}"

    @property
    def is_connected(self) -> bool:
        return self.receive.recv is not None and self.line.ctrl is not None

    @property
    def needs_reconnect(self) -> bool:
        """Either interface lost the controller, the control interface was abandoned, or the
        control script stopped under us.

        ur-rtde never brings a lost receive interface back, and its control interface's own
        reconnect gives up after one try while the controller is away, so a controller that
        rebooted or got its cable back is only used again through ``disconnect()`` and
        ``connect()`` (the node's ``DeviceRecovery`` does that off the frame loop).
        """
        line = self.line
        recv, ctrl = self.receive.recv, line.ctrl
        if line.broken is None and line.program_lost is None and recv is not None:
            # not the keep-alive's turns alone: a kick sent as the script stopped waits inside
            # ur-rtde for a "ready" that never comes (4 s), and the stop went unnoticed as long
            self.watchdog.notice_program_stop(recv)
        if line.broken is not None or line.program_lost is not None:
            return True
        if recv is None or ctrl is None:
            return False
        return not (recv.isConnected() and ctrl.isConnected())

    def connect(self) -> None:
        if self.is_connected:
            raise DeviceAlreadyConnectedError(f"URArm at {self.config.host} is already connected")
        for attempt in range(1, WATCHDOG_ARM_TRIES + 1):
            try:
                self._connect_once()
                return
            except WatchdogArmingLostError as e:
                if attempt == WATCHDOG_ARM_TRIES:
                    raise
                log.warning("%s; connecting again (%d of %d)", e, attempt + 1, WATCHDOG_ARM_TRIES)

    def _connect_once(self) -> None:
        recv, ctrl, ctrl_tids = open_interfaces(self.config)
        self.receive.open(recv)
        # ur-rtde's control thread real-time while a call waits on it, one step under the
        # keep-alive, where this process runs real-time (the arm process)
        level = max(1, self.realtime_priority - 1) if self.realtime_priority else 0
        self.line.open(ctrl, ControlReceiver(ctrl_tids, level))
        self.motion.reset()
        # the kicking thread first: started after the watchdog, its start-up in a busy
        # process was once longer than the window ("0 kicks", a trip at every connect)
        self._start_deadman()
        try:
            self.watchdog.arm()
        except DeviceError:
            self.disconnect()
            raise
        # from here on a late kick can stop the arm: the keep-alive's timing counts from now
        self.keep_alive_periods.clear()
        log.info(
            "URArm connected to %s (watchdog %.0f ms)",
            self.config.host,
            self.config.watchdog_window_s * 1000,
        )

    def disconnect(self) -> None:
        """Stop the arm, end the control script, close both interfaces, whatever fails."""
        if not self.is_connected:
            return
        line = self.line
        try:
            try:
                with self._lock:
                    # once the script is known to have stopped there is nothing left to tell it
                    if line.program_lost is None:
                        try:
                            self._stop_locked()
                        except DeviceError as e:
                            log.warning("URArm: stop on disconnect failed: %s", e)
            finally:
                # Only now: the keep-alive kicks on until the stop is on the wire (a kick waits
                # for no call). Ended first, a busy PC's gap between its last kick and the stop
                # could pass the watchdog window (a trip while the arm process stopped the arm
                # of a killed node, beside two busy loops).
                self._stop_deadman()
            with self._lock:
                if line.program_lost is None:
                    line.ending_script = True  # the script's end that follows is ours
                    try:
                        line.call("stopScript", line.ctrl.stopScript)
                    except DeviceError as e:
                        log.warning("URArm: stopScript on disconnect failed: %s", e)
        finally:
            close_interfaces(self.receive.close(), line.close(), line.broken)
            log.info("URArm disconnected from %s", self.config.host)

    # -- what the Arm asks of its driver ------------------------------------------

    def _read_tcp_pose(self) -> np.ndarray:
        return self.receive.tcp_pose()

    def _read_joints(self) -> np.ndarray:
        return self.receive.joints()

    def _send_jog(self, velocity: np.ndarray) -> None:
        self.motion.jog(velocity)

    def _send_move(self, pose: np.ndarray, speed: float) -> None:
        self.motion.move(pose, speed)

    def _move_finished(self) -> bool:
        return self.motion.move_finished()

    def _send_stop(self) -> None:
        self.motion.stop()

    def _keep_alive(self) -> None:
        self.watchdog.keep_alive()

    def _watch_spins(self) -> None:
        self.line.spin_guard.check()

    def _deadman_stop_limit_s(self) -> float:
        return self.motion.stop_limit_s()

    def move_to(self, pose: Any, speed: float | None = None, wait: bool = True) -> None:
        """As ``Arm.move_to``; after a watchdog trip it first reconnects (a fresh script).

        A move is an absolute target asked for now, not a velocity that was
        right only when it was sent: a jog after a trip is refused instead, and
        the node's recovery reconnects.
        """
        if self.line.program_lost is not None:
            log.warning("URArm: reconnecting for a move: %s", self.line.program_lost)
            self.disconnect()
            self.connect()
        super().move_to(pose, speed, wait)

    # -- what it reports ---------------------------------------------------------

    def live_readings(self) -> dict[str, float]:
        """The receive stream's newest TCP pose and speed (``ReceiveSide.live_readings``);
        nothing once the program stopped under us."""
        if self.line.program_lost is not None:
            return {}
        return self.receive.live_readings()

    def driver_state(self) -> dict[str, float]:
        """Adds the controller's safety mode and program state (RTDE cache reads); raises
        once the program stopped under us, or the stream is lost or stale."""
        if self.line.program_lost is not None:  # the node's poll then reconnects at once
            raise DeviceError(f"URArm: {self.line.program_lost}")
        out = super().driver_state()
        if self.is_connected:
            recv = self.receive.fresh()
            out["arm_safety_mode"] = float(int(recv.getSafetyMode()))
            # robot_status_bits: bit 1 is "program running" (the control script)
            out["arm_program_running"] = float(bool(int(recv.getRobotStatus()) & 2))
        return out

    def telemetry(self) -> dict[str, float]:
        """Adds the controller's TCP speed to ``driver_state`` and the rest."""
        out = super().telemetry()
        if self.is_connected:
            speed = np.asarray(self.receive.fresh().getActualTCPSpeed(), dtype=float)
            out["arm_speed_m_s"] = float(np.linalg.norm(speed[:3]))
            out["arm_angular_speed_rad_s"] = float(np.linalg.norm(speed[3:]))
        return out

    def status(self) -> dict[str, Any]:
        out = super().status()
        line = self.line
        out.update(
            host=self.config.host,
            stale_events=self.receive.stale_events,
            watchdog_window_ms=self.config.watchdog_window_s * 1000,
            watchdog_kicks=self.watchdog.kicks,
            longest_silence_ms=round(line.silence_max_s * 1000, 1),
            spins_made_fair=line.spin_guard.demotions,
        )
        if line.program_lost is not None:
            out["program_lost"] = line.program_lost
        if self.is_connected:
            out["safety"] = self.receive.safety_text()
            out["program_running"] = line.program_running()
            out["data_age_ms"] = round(self.receive.data_age_s() * 1000, 1)
            if line.broken:
                out["control_broken"] = line.broken
        return out
