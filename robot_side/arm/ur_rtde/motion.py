"""Jogs, moves and stops on the control line, and the accelerations they use.

Jogging uses ``speedL``, not ``jogStart``: speedL is one of the script's
realtime commands (the call writes the registers and returns in about
0.1 ms, no handshake), it takes base-frame velocities, which is what the
operator's jog is, and its deceleration is ours to choose. jogStart waits
for a full command handshake per update. Neither stops by itself; the
deadman in :class:`~robot_side.arm.base.Arm` does.

No kick may interrupt a command's handshake (it would overwrite the command
register), so a stop never waits for the deceleration on the wire: a jog is
stopped by a realtime ``speedL`` to zero at the stop's deceleration (no
handshake) and, once the receive stream shows the arm at rest, ``speedStop``
ends the script's speed thread (a handshake of a few controller cycles); a
move by an asynchronous ``stopL``. The kicks go on while the arm decelerates.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from common.clocks.clock import now_s
from common.errors import DeviceError, DeviceNotConnectedError
from common.wire.messages import ARM_SAFETY_MODES
from robot_side.arm.base import ArmLimits
from robot_side.arm.ur_rtde.config import URArmConfig
from robot_side.arm.ur_rtde.control import ArmCommandRefusedError, ControlLine
from robot_side.arm.ur_rtde.keep_alive import ControllerWatchdog
from robot_side.arm.ur_rtde.receive import ReceiveSide, at_rest

log = logging.getLogger(__name__)

#: a stop must end within this share of the watchdog window, however fast the wrist turned
#: (see stop_acceleration): where the receive stream cannot be read, the stop's handshake
#: waits for the whole deceleration with no kick (keep_alive)
STOP_WITHIN_WINDOW = 0.5
#: how long after the deceleration should have ended a stop still waits for the receive stream
#: to show the arm at rest before it sends its handshake anyway
REST_CATCH_UP_S = 0.05
#: After a move ends on the control connection, how long move_to waits for the receive stream
#: (another connection, cached by its own thread) to show the arm at rest: on a busy machine
#: its newest package was still from the move's last milliseconds, 23 um short of the target.
MOVE_CATCH_UP_S = 0.1


class Motion:
    """What this driver set moving (a jog's speed thread, a move), and how it stops it."""

    def __init__(
        self,
        config: URArmConfig,
        limits: ArmLimits,
        receive: ReceiveSide,
        line: ControlLine,
        watchdog: ControllerWatchdog,
    ) -> None:
        self.config = config
        self.limits = limits
        self.receive = receive
        self.line = line
        self.watchdog = watchdog
        self.speeding = False  # the script's speed thread runs (a jog)
        self.moving = False  # a moveL runs
        self._move_ended_at: float | None = None  # when the control connection said so

    def reset(self) -> None:
        """A fresh script moves nothing."""
        self.speeding = self.moving = False

    def jog(self, velocity: np.ndarray) -> None:
        ctrl = self.line.ctrl
        self._check_safety("jog")
        if self.moving:
            self._stop_move()
        ok = self.line.call(
            "speedL",
            ctrl.speedL,
            velocity.tolist(),
            self.jog_acceleration(velocity),
            0.0,
            realtime=True,
        )
        self.watchdog.check(ok, "speedL")
        self.speeding = True

    def move(self, pose: np.ndarray, speed: float) -> None:
        ctrl = self.line.ctrl
        self._check_safety("move")
        if self.speeding:
            self._stop_speed()
        self.moving = True
        self._move_ended_at = None
        ok = self.line.call(
            "moveL", ctrl.moveL, pose.tolist(), speed, self.limits.linear_acceleration_m_s2, True
        )
        self.watchdog.check(ok, "moveL")

    def move_finished(self) -> bool:
        self.receive.fresh()  # a vanished or silent controller must not look like a finished move
        line = self.line
        if line.broken is not None or not line.ctrl.isConnected():
            raise DeviceNotConnectedError(
                f"URArm: lost the control connection to {self.config.host} during a move"
            )
        if line.ctrl.getAsyncOperationProgress() >= 0:
            return False
        now = now_s()
        if self._move_ended_at is None:
            self._move_ended_at = now
        moving = not at_rest(self.receive.tcp_speed())
        if moving and now - self._move_ended_at < MOVE_CATCH_UP_S:
            return False  # the receive stream has not caught up: the pose read next would lag
        self.moving = False
        self._move_ended_at = None
        return True

    def stop(self) -> None:
        """A jog's speed thread and a move each stopped as above; a still arm costs no handshake.

        Every handshake is silence on the wire (no kick may interrupt it), so a
        stop of an arm this driver knows to be still (a repeated stop, a
        released key after a STOP) sends nothing, unless the receive stream
        shows the TCP moving or cannot be read: then both stops go.
        """
        if self.line.program_lost is not None:
            log.debug("URArm: stop: no control script runs; the controller stopped the arm")
            self.speeding = self.moving = False
            return
        unknown = not (self.speeding or self.moving) and not self.receive.seen_at_rest()
        errors = []
        for step in (
            self._stop_speed if self.speeding or unknown else None,
            self._stop_move if self.moving or unknown else None,
        ):
            if step is None:
                continue
            try:
                step()
            except DeviceError as e:
                errors.append(e)
        if errors and self.line.program_lost is None:  # else the controller stopped the arm
            raise errors[0]

    def decel_time(self) -> float:
        return max(
            self.limits.max_linear_speed_m_s / self.limits.stop_deceleration_m_s2,
            STOP_WITHIN_WINDOW * self.config.watchdog_window_s,
        )

    def stop_limit_s(self) -> float:
        """A stop's two calls, each with its deadline and the wait for rest between."""
        return 2 * (self.config.command_timeout_s + self.decel_time() + REST_CATCH_UP_S)

    def jog_acceleration(self, velocity: np.ndarray) -> float:
        """speedL's one acceleration, which the controller applies to the turn too (rad/s^2).

        URScript's ``speedl(xd, a)``: ``aRot`` defaults to ``a``, and ur-rtde passes no
        ``aRot``. A pure wrist turn therefore ramps at the angular limit; a jog that
        translates at the lower of the two, so neither part exceeds its own.
        """
        lim = self.limits
        if not np.any(velocity[:3]):
            return lim.angular_acceleration_rad_s2
        return min(lim.linear_acceleration_m_s2, lim.angular_acceleration_rad_s2)

    def stop_acceleration(self) -> float:
        """The stop's one acceleration: the limits' gentle one, or more if the wrist turns fast.

        ur-rtde's stops take one acceleration, and the controller decelerates a rotation at
        the same number in rad/s^2 (URScript ``stopl(a)``: ``aRot`` defaults to ``a``). From
        the 0.5 rad/s cap at 2 rad/s^2 a stop took 250 ms, waiting unkicked on the script:
        the watchdog (150 ms) tripped on every fast wrist turn's stop. A translation keeps its
        gentle stop (a held pipette feels it); a turn stops within half the window.
        """
        try:
            turning = float(np.linalg.norm(self.receive.fresh().getActualTCPSpeed()[3:]))
        except DeviceError:  # cannot see it: assume the cap
            turning = self.limits.max_angular_speed_rad_s
        if not np.isfinite(turning):
            turning = self.limits.max_angular_speed_rad_s
        within = STOP_WITHIN_WINDOW * self.config.watchdog_window_s
        return max(self.limits.stop_deceleration_m_s2, turning / within)

    def _check_safety(self, what: str) -> None:
        """Refuse motion in a safety stop up front: ur-rtde may report success into it."""
        mode = int(self.receive.recv.getSafetyMode())
        if mode not in (1, 2):  # normal, reduced
            raise ArmCommandRefusedError(
                f"URArm: {what} refused: the robot is in {ARM_SAFETY_MODES.get(mode, mode)}; "
                "clear it on the pendant, then disconnect() and connect() again"
            )

    def _stop_speed(self) -> None:
        """Decelerate with the wire free for kicks, then end the script's speed thread at rest.

        ``speedStop`` waits for the script's "done", which comes after the whole
        deceleration (75 ms from the wrist's cap), and no kick may interrupt a
        handshake: that silence left 60 ms of margin to the watchdog window and
        tripped it on a busy machine. A ``speedL`` to zero at the same
        deceleration is realtime (no handshake), so the keep-alive thread goes
        on kicking while the arm decelerates, and the ``speedStop`` that follows
        at rest is a few controller cycles.
        """
        a = self.stop_acceleration()
        line = self.line
        ok = line.call("speedL to rest", line.ctrl.speedL, [0.0] * 6, a, 0.0, realtime=True)
        self.watchdog.check(ok, "speedL to rest")
        self._wait_at_rest()
        ok = line.call("speedStop", line.ctrl.speedStop, a, extra_s=self.decel_time())
        self.speeding = False
        self.watchdog.check(ok, "speedStop")

    def _stop_move(self) -> None:
        """A move in progress is stopped asynchronously (the wire free for kicks), then awaited."""
        line = self.line
        if not self.moving:  # nothing this driver started moves: a short handshake
            line.call("stopL", line.ctrl.stopL, self.stop_acceleration(), False)
            return
        line.call(
            "stopL", line.ctrl.stopL, self.stop_acceleration(), True, extra_s=self.decel_time()
        )
        self.moving = False
        self._wait_at_rest()

    def _wait_at_rest(self) -> None:
        """Until the receive stream shows the TCP at rest, or the deceleration's time is up.

        The wire lock is not held: the keep-alive thread kicks meanwhile. A
        stream that cannot be read ends the wait at once (the handshake that
        follows then waits for the deceleration itself).
        """
        deadline = now_s() + self.decel_time() + REST_CATCH_UP_S
        while not self.receive.seen_at_rest():
            if now_s() >= deadline:
                log.debug("URArm: the arm still moves after the stop's deceleration")
                return
            time.sleep(0.002)
