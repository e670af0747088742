"""UR3e through ur-rtde: RTDEReceiveInterface for state, RTDEControlInterface for motion.

What ur-rtde does when the controller goes away shapes this driver
(measured against the simulator, see docs/arm.md):

- Receive getters keep returning the last cached values. Every read here
  checks ``isConnected()`` and that the controller timestamp still advances;
  otherwise it raises instead of handing out an old pose.
- Control calls that wait for the script's "done" (speedStop, stopL, moveL,
  stopScript) retry a vanished controller forever, and realtime ones
  (speedL) report success into the void. So each control call first checks
  ``isConnected()`` and then runs on a worker thread with a deadline (ur-rtde
  releases the GIL in those calls): a stuck call becomes a
  ``DeviceTimeoutError`` and the driver is marked unusable, never a hang.
- The constructors hold the GIL while they talk to the controller, so a
  simulator must not share this process (the "simulated" kind runs it in a
  child process).
- RTDEIOInterface aborts the whole process when its server vanishes: not used.

Jogging uses ``speedL``, not ``jogStart``: speedL is one of the script's
realtime commands (the call writes the registers and returns in about
0.1 ms, no handshake), it takes base-frame velocities, which is what the
operator's jog is, and its deceleration is ours to choose. jogStart waits
for a full command handshake per update. Neither stops by itself; the
deadman in :class:`~robot_side.arm.base.Arm` does.
"""

from __future__ import annotations

import concurrent.futures
import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from common.clock import now_s
from common.config import param
from common.errors import (
    DeviceAlreadyConnectedError,
    DeviceError,
    DeviceNotConnectedError,
    DeviceTimeoutError,
    StaleDataError,
)
from common.messages import ARM_SAFETY_MODES
from common.preflight import Finding, PreflightContext, tcp_findings
from robot_side.arm.base import Arm, ArmLimits

log = logging.getLogger(__name__)

#: What the receive interface streams: only what this driver reads (less to parse at 500 Hz).
RECEIVE_VARIABLES = [
    "timestamp",
    "actual_q",
    "actual_TCP_pose",
    "actual_TCP_speed",
    "robot_mode",
    "safety_mode",
    "runtime_state",
    "robot_status_bits",
    "safety_status_bits",
]


#: ur-rtde's fixed ports on the controller: RTDE, dashboard, the script port.
CONTROLLER_PORTS = {30004: "RTDE", 29999: "dashboard", 30003: "script"}

#: Control interfaces with a call stuck inside (see ``_control``), kept so no destructor runs.
_ABANDONED: list[Any] = []


class _Worker:
    """One daemon thread running control calls in order.

    Not a ThreadPoolExecutor: its threads are joined at interpreter exit, so a
    call stuck in ur-rtde's reconnect loop would hang the process at exit.
    """

    def __init__(self, name: str) -> None:
        self._jobs: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def submit(self, fn: Callable[..., Any], *args: Any) -> concurrent.futures.Future[Any]:
        future: concurrent.futures.Future[Any] = concurrent.futures.Future()
        self._jobs.put((future, fn, args))
        return future

    def shutdown(self) -> None:
        self._jobs.put(None)

    def _run(self) -> None:
        while (job := self._jobs.get()) is not None:
            future, fn, args = job
            if not future.set_running_or_notify_cancel():
                continue
            try:
                future.set_result(fn(*args))
            except BaseException as e:  # handed to the caller through the future
                future.set_exception(e)


class ArmCommandRefusedError(DeviceError):
    """The controller refused a command (script not running, protective stop, ...)."""


#: A controller frees the previous session's RTDE inputs when it sees the
#: close; a reconnect right after a disconnect can arrive first.
CONTROL_CONNECT_TRIES = 5
CONTROL_CONNECT_RETRY_S = 0.2


@dataclass
class URArmConfig:
    host: str = param("192.168.1.10", "the UR controller's IP (pendant: Settings > Network)")
    frequency_hz: float = param(500.0, "RTDE receive rate; the e-Series streams up to 500 Hz")
    stale_after_s: float = param(
        0.1, "a controller timestamp frozen this long means it stopped streaming: reads raise"
    )
    command_timeout_s: float = param(
        2.0, "a control call still busy after this (plus any deceleration) is abandoned"
    )
    limits: ArmLimits = param(ArmLimits(), "workspace box, speed caps and the jog deadman")


class URArm(Arm):
    Config = URArmConfig

    def __init__(self, config: URArmConfig | None = None) -> None:
        self.config = config or URArmConfig()
        super().__init__(self.config.limits)
        self._recv: Any = None
        self._ctrl: Any = None
        self._worker: _Worker | None = None
        self._ctrl_broken: str | None = None
        self._speeding = False
        self._moving = False
        self._last_ts = -1.0
        self._last_ts_change = 0.0
        self._stale_events = 0

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
        return self._recv is not None and self._ctrl is not None

    @property
    def needs_reconnect(self) -> bool:
        """The control interface was abandoned after a call missed its deadline."""
        return self._ctrl_broken is not None

    def connect(self) -> None:
        if self.is_connected:
            raise DeviceAlreadyConnectedError(f"URArm at {self.config.host} is already connected")
        import rtde_control
        import rtde_receive

        host = self.config.host
        hint = (
            f"check that the UR controller at {host} is on, reachable (ping it), in remote "
            "control, and that no other program holds its RTDE inputs"
        )
        try:
            recv = rtde_receive.RTDEReceiveInterface(
                host, self.config.frequency_hz, RECEIVE_VARIABLES
            )
        except RuntimeError as e:
            msg = f"URArm: RTDE receive to {host} failed ({e}); {hint}"
            raise DeviceNotConnectedError(msg) from e
        ctrl = None
        for attempt in range(CONTROL_CONNECT_TRIES):
            try:
                ctrl = rtde_control.RTDEControlInterface(host)
                break
            except RuntimeError as e:
                # Right after a disconnect the controller may still hold our previous
                # session's input registers; they are freed when it sees the close.
                if "already in use" in str(e) and attempt + 1 < CONTROL_CONNECT_TRIES:
                    log.info("URArm: RTDE inputs at %s still held; trying again", host)
                    time.sleep(CONTROL_CONNECT_RETRY_S)
                    continue
                recv.disconnect()
                msg = f"URArm: RTDE control to {host} failed ({e}); {hint}"
                raise DeviceNotConnectedError(msg) from e
        self._recv, self._ctrl = recv, ctrl
        self._ctrl_broken = None
        self._speeding = self._moving = False
        self._worker = _Worker(f"urarm-ctrl-{host}")
        self._last_ts = recv.getTimestamp()
        self._last_ts_change = now_s()
        self._start_deadman()
        log.info("URArm connected to %s", host)

    def disconnect(self) -> None:
        """Stop the arm, end the control script, close both interfaces, whatever fails."""
        if not self.is_connected:
            return
        self._stop_deadman()
        recv, ctrl = self._recv, self._ctrl
        try:
            with self._lock:
                try:
                    self._stop_locked()
                except DeviceError as e:
                    log.warning("URArm: stop on disconnect failed: %s", e)
                try:
                    self._control("stopScript", ctrl.stopScript)
                except DeviceError as e:
                    log.warning("URArm: stopScript on disconnect failed: %s", e)
        finally:
            self._recv = self._ctrl = None
            if self._ctrl_broken is not None:
                # a call is stuck inside it; destroying it now would block on that call
                log.warning("URArm: control interface abandoned: %s", self._ctrl_broken)
                _ABANDONED.append(ctrl)
            if self._worker is not None:
                self._worker.shutdown()
                self._worker = None
            # ur-rtde's destructors disconnect (each sleeps 0.5 s with the GIL held);
            # an explicit disconnect() first would only add another 0.5 s.
            del recv, ctrl
            log.info("URArm disconnected from %s", self.config.host)

    # -- receive side --------------------------------------------------------

    def _fresh(self) -> Any:
        """The receive interface, after checking that its cache is live."""
        recv = self._recv
        if recv is None:
            self.require_connected()
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
            self._stale_events += 1
            raise StaleDataError(
                f"URArm: the controller timestamp has not advanced for "
                f"{(now - self._last_ts_change) * 1000:.0f} ms (limit "
                f"{self.config.stale_after_s * 1000:.0f} ms): it stopped streaming. "
                "Check the controller; reconnect if it does not recover"
            )
        return recv

    def _read_tcp_pose(self) -> np.ndarray:
        return np.asarray(self._fresh().getActualTCPPose(), dtype=float)

    def _read_joints(self) -> np.ndarray:
        return np.asarray(self._fresh().getActualQ(), dtype=float)

    def tcp_speed(self) -> np.ndarray:
        self.require_connected()
        return np.asarray(self._fresh().getActualTCPSpeed(), dtype=float)

    def controller_timestamp(self) -> float:
        """Seconds since the controller booted, as the last data package said."""
        self.require_connected()
        return float(self._fresh().getTimestamp())

    def _safety_text(self) -> str:
        try:
            mode = int(self._recv.getSafetyMode())
        except Exception:  # only used to word an error message
            return "unknown"
        return ARM_SAFETY_MODES.get(mode, f"mode {mode}")

    # -- control side --------------------------------------------------------

    def _control(
        self,
        what: str,
        fn: Callable[..., Any],
        *args: Any,
        extra_s: float = 0.0,
        realtime: bool = False,
    ) -> Any:
        """Run one ur-rtde control call with a deadline (see the module docstring).

        ``realtime`` calls (speedL) only write registers and never wait, even
        for a vanished controller (measured), so they skip the worker thread
        and its hand-off, which costs milliseconds on a busy machine.
        """
        ctrl = self._ctrl
        if ctrl is None or self._worker is None:
            self.require_connected()
        if self._ctrl_broken is not None:
            raise DeviceError(
                f"URArm: control interface unusable ({self._ctrl_broken}); disconnect() and "
                "connect() again"
            )
        if not ctrl.isConnected():
            raise DeviceNotConnectedError(
                f"URArm: lost the control connection to {self.config.host} before {what}; "
                "the controller's own stop applies. disconnect() and connect() again"
            )
        if realtime:
            try:
                return fn(*args)
            except RuntimeError as e:
                raise DeviceError(f"URArm: {what} failed: {e}") from e
        future = self._worker.submit(fn, *args)
        timeout = self.config.command_timeout_s + extra_s
        try:
            return future.result(timeout=timeout)
        except concurrent.futures.TimeoutError:
            self._ctrl_broken = f"{what} did not return in {timeout:.1f} s"
            raise DeviceTimeoutError(
                f"URArm: {what} did not return in {timeout:.1f} s (ur-rtde keeps retrying a "
                f"controller that went away); check {self.config.host}, then reconnect"
            ) from None
        except RuntimeError as e:
            raise DeviceError(f"URArm: {what} failed: {e}") from e

    def _check(self, ok: Any, what: str) -> None:
        if ok is False:
            raise ArmCommandRefusedError(
                f"URArm: the controller refused {what} (safety: {self._safety_text()}, "
                f"program running: {self._program_running()}); clear any stop on the pendant "
                "and reconnect"
            )

    def _program_running(self) -> bool | str:
        try:
            return bool(self._ctrl.isProgramRunning())
        except Exception:  # only used to word an error message
            return "unknown"

    def _check_safety(self, what: str) -> None:
        """Refuse motion in a safety stop up front: ur-rtde may report success into it."""
        mode = int(self._recv.getSafetyMode())
        if mode not in (1, 2):  # normal, reduced
            raise ArmCommandRefusedError(
                f"URArm: {what} refused: the robot is in {ARM_SAFETY_MODES.get(mode, mode)}; "
                "clear it on the pendant, then disconnect() and connect() again"
            )

    def _send_jog(self, velocity: np.ndarray) -> None:
        ctrl = self._ctrl
        self._check_safety("jog")
        if self._moving:
            self._stop_move()
        ok = self._control(
            "speedL",
            ctrl.speedL,
            velocity.tolist(),
            self.limits.linear_acceleration_m_s2,
            0.0,
            realtime=True,
        )
        self._check(ok, "speedL")
        self._speeding = True

    def _send_move(self, pose: np.ndarray, speed: float) -> None:
        ctrl = self._ctrl
        self._check_safety("move")
        if self._speeding:
            self._stop_speed()
        self._moving = True
        ok = self._control(
            "moveL", ctrl.moveL, pose.tolist(), speed, self.limits.linear_acceleration_m_s2, True
        )
        self._check(ok, "moveL")

    def _move_finished(self) -> bool:
        self._fresh()  # a vanished or silent controller must not look like a finished move
        if self._ctrl_broken is not None or not self._ctrl.isConnected():
            raise DeviceNotConnectedError(
                f"URArm: lost the control connection to {self.config.host} during a move"
            )
        if self._ctrl.getAsyncOperationProgress() >= 0:
            return False
        self._moving = False
        return True

    def _decel_time(self) -> float:
        return self.limits.max_linear_speed_m_s / self.limits.stop_deceleration_m_s2

    def _stop_speed(self) -> None:
        ok = self._control(
            "speedStop",
            self._ctrl.speedStop,
            self.limits.stop_deceleration_m_s2,
            extra_s=self._decel_time(),
        )
        self._speeding = False
        self._check(ok, "speedStop")

    def _stop_move(self) -> None:
        self._control(
            "stopL",
            self._ctrl.stopL,
            self.limits.stop_deceleration_m_s2,
            False,
            extra_s=self._decel_time(),
        )
        self._moving = False

    def _send_stop(self) -> None:
        """speedStop ends a jog's speed thread; stopL ends a move (and anything else)."""
        errors = []
        for step in (self._stop_speed if self._speeding else None, self._stop_move):
            if step is None:
                continue
            try:
                step()
            except DeviceError as e:
                errors.append(e)
        if errors:
            raise errors[0]

    def telemetry(self) -> dict[str, float]:
        """Adds the controller's TCP speed, safety mode and program state (RTDE cache reads)."""
        out = super().telemetry()
        if self.is_connected:
            recv = self._fresh()
            speed = np.asarray(recv.getActualTCPSpeed(), dtype=float)
            out["arm_speed_m_s"] = float(np.linalg.norm(speed[:3]))
            out["arm_angular_speed_rad_s"] = float(np.linalg.norm(speed[3:]))
            out["arm_safety_mode"] = float(int(recv.getSafetyMode()))
            # robot_status_bits: bit 1 is "program running" (the control script)
            out["arm_program_running"] = float(bool(int(recv.getRobotStatus()) & 2))
        return out

    def status(self) -> dict[str, Any]:
        out = super().status()
        out.update(host=self.config.host, stale_events=self._stale_events)
        if self.is_connected:
            out["safety"] = self._safety_text()
            out["program_running"] = self._program_running()
            out["data_age_ms"] = round((now_s() - self._last_ts_change) * 1000, 1)
            if self._ctrl_broken:
                out["control_broken"] = self._ctrl_broken
        return out
