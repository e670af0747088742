"""The controller's watchdog: armed at connect, kicked while this process lives.

The jog deadman lives in this process, so the controller must also stop the
arm when this process cannot (``kill -9``, ``SIGSTOP``, a wedged
interpreter): connect arms ur-rtde's watchdog (``setWatchdog``: the control
script calls ``rtde_set_watchdog("input_int_register_0", 1 / watchdog_window_s,
"stop")``) and the keep-alive thread of :class:`~robot_side.arm.base.Arm`
kicks it every deadman period (``kickWatchdog`` writes 0 to that register;
any command does too), while the deadman thread is responsive. When no
update arrives for ``watchdog_window_s`` the controller stops the program,
and the arm with it. A script that stopped while the safety mode stayed
normal (that trip, or a stop on the pendant) makes the driver refuse every
command and ask for a reconnect, which uploads a fresh script with a cleared
command register: nothing sent before the stop can move the arm after it.
docs/arm.md has the stop budget.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

from common.clocks.clock import now_s
from common.errors import DeviceError, DeviceNotConnectedError
from common.logs import BurstLog
from robot_side.arm.base import ArmLimits
from robot_side.arm.ur_rtde.config import URArmConfig
from robot_side.arm.ur_rtde.control import ArmCommandRefusedError, ControlLine
from robot_side.arm.ur_rtde.receive import ReceiveSide

log = logging.getLogger(__name__)

#: How many times connect() uploads the script and arms the watchdog. The controller counts
#: the window from the moment it arms the watchdog, and ur-rtde's next update goes out only
#: once this process has read the script's answer: a process starved that long at connect (a
#: busy robot PC starting its node) lost its script to the watchdog before the first kick.
WATCHDOG_ARM_TRIES = 3

#: A kick writes 0 to the command register. Within one controller cycle (2 ms on an e-Series,
#: 8 ms on a CB3) after a speedL it could overwrite the command before the script read it, so
#: no kick follows a command sooner than this; that command updated the register itself.
KICK_AFTER_COMMAND_S = 0.01

#: How long a refused command waits for the receive stream to show the stopped script.
REFUSAL_CATCH_UP_S = 0.05


class WatchdogArmingLostError(DeviceNotConnectedError):
    """The control script stopped while connect() armed its watchdog; connecting again may work."""


class ControllerWatchdog:
    """Arms the watchdog, kicks it (``keep_alive``) and notices the script it stopped.

    ``deadman_responsive`` says whether the arm's deadman thread could still
    stop a jog: the kicks vouch for it, so none go while it cannot.
    """

    def __init__(
        self,
        config: URArmConfig,
        limits: ArmLimits,
        receive: ReceiveSide,
        line: ControlLine,
        deadman_responsive: Callable[[], bool],
    ) -> None:
        self.config = config
        self.limits = limits
        self.receive = receive
        self.line = line
        self.deadman_responsive = deadman_responsive
        self.kicks = 0
        self._kicks_withheld = BurstLog(log, "URArm")
        self._keep_alive_ran = (0.0, 0.0)  # monotonic s: the keep-alive thread's last two turns

    def arm(self) -> None:
        """From here on the controller stops the arm whenever this process falls silent.

        Raises ``WatchdogArmingLostError`` when the script stopped meanwhile
        (connecting again may work), else ``DeviceNotConnectedError``; the
        caller disconnects.
        """
        line = self.line
        line.silence_max_s, self.kicks = 0.0, 0
        try:
            hz = 1.0 / self.config.watchdog_window_s
            ok = line.call("setWatchdog", line.ctrl.setWatchdog, hz)
            self.check(ok, "setWatchdog")
        except DeviceError as e:
            lost = line.program_lost
            if lost is not None:
                # the script stopped while it armed the watchdog: the controller's answer
                # reached this process later than the window (above), or someone stopped it
                raise WatchdogArmingLostError(
                    f"URArm: the control script at {self.config.host} stopped while it armed the "
                    f"watchdog ({lost}): this process read the controller's answer later than "
                    f"the {self.config.watchdog_window_s * 1000:.0f} ms window, as on a busy PC; "
                    "the arm is not connected"
                ) from e
            raise DeviceNotConnectedError(
                f"URArm: could not arm the controller's watchdog at {self.config.host} ({e}); "
                "without it a dead node would leave the arm moving, so the arm is not connected"
            ) from e
        line.watched_since = float(self.receive.recv.getTimestamp())

    def keep_alive(self) -> None:
        """Kick the watchdog unless a command just did; notice a script that stopped under us.

        Called every deadman period on the keep-alive thread; never waits: a
        kick while another call is on the wire is skipped, since that call
        writes the register itself and a kick in the middle of its handshake
        would overwrite the command before the script read it. No kick while
        the deadman thread is stuck: the kicks also vouch for it.
        """
        self._keep_alive_ran = (self._keep_alive_ran[1], now_s())
        line = self.line
        recv, ctrl = self.receive.recv, line.ctrl
        if (
            line.watched_since is None
            or recv is None
            or ctrl is None
            or line.broken is not None
            or line.program_lost is not None
        ):
            return
        self.notice_program_stop(recv)
        if line.program_lost is not None or now_s() - line.last_sent < KICK_AFTER_COMMAND_S:
            return
        if not self.deadman_responsive():
            # a deadman that cannot stop a jog must not be covered for: the controller stops it
            self._kicks_withheld(
                "the deadman thread is starved (a jog outlived its deadline, or the thread has "
                f"not woken for {self.limits.jog_timeout_s:g} s): kicks withheld, the "
                "controller's watchdog stops the arm"
            )
            return
        if line.kick(ctrl):
            self.kicks += 1

    def notice_program_stop(self, recv: Any, refused: bool = False) -> None:
        """The control script stopped while the safety mode is normal: a watchdog trip or a stop.

        Seen in the receive stream: every deadman period (only in data sent
        after the script was certainly running), and when ur-rtde ``refused`` a
        command. A protective or emergency stop is left to the motion's safety
        check, which names it.
        """
        line = self.line
        if line.program_lost is not None or line.ending_script:
            return  # known already, or this process is ending the script (disconnect)
        try:
            if not refused and int(recv.getRobotStatus()) & 2:
                return  # the script runs: every turn but the one that matters, in one read
            if not recv.isConnected():
                return
            armed = line.watched_since
            if not refused and (armed is None or float(recv.getTimestamp()) < armed + 0.01):
                return
            # ur-rtde refused on its control connection's view, which may be a package or
            # two ahead of ours: give ours a moment to show the stop too
            deadline = now_s() + (REFUSAL_CATCH_UP_S if refused else 0.0)
            while int(recv.getRobotStatus()) & 2:
                if now_s() >= deadline:
                    return
                time.sleep(0.002)
            # the status first: a safety mode read after it is from the same package or a
            # newer one, so a protective stop that ended the program is seen as one
            if int(recv.getSafetyMode()) not in (1, 2):
                return
        except RuntimeError:
            return
        line.program_lost = (
            f"the control script on {self.config.host} stopped with the safety mode normal: "
            f"the watchdog ({self.config.watchdog_window_s * 1000:.0f} ms) tripped, or someone "
            "pressed stop on the pendant or the dashboard; the controller stopped the arm. "
            "Reconnect to upload the script again"
        )
        # which of the two it was: a call that held the wire (no kick may interrupt it), or a
        # keep-alive thread that did not run (the CPU or the GIL kept from it)
        now = now_s()
        log.warning(
            "URArm: %s (this process last wrote to the controller %.0f ms ago: %s; a call %s "
            "the wire; the keep-alive thread's last two turns were %.0f and %.0f ms ago; the "
            "longest silence since connect was %.0f ms; %d kicks)",
            line.program_lost,
            (now - line.last_sent) * 1000,
            line.last_sent_what,
            "holds" if line.wire.locked() else "does not hold",
            (now - self._keep_alive_ran[0]) * 1000,
            (now - self._keep_alive_ran[1]) * 1000,
            line.silence_max_s * 1000,
            self.kicks,
        )

    def check(self, ok: Any, what: str) -> None:
        """A call ur-rtde answered False: the script stopped under us, or the controller
        refused the command (a stop on the pendant, a protective stop)."""
        if ok is False:
            self.notice_program_stop(self.receive.recv, refused=True)
            if self.line.program_lost is not None:
                raise DeviceError(f"URArm: {what} refused: {self.line.program_lost}")
            raise ArmCommandRefusedError(
                f"URArm: the controller refused {what} (safety: {self.receive.safety_text()}, "
                f"program running: {self.line.program_running()}); clear any stop on the "
                "pendant and reconnect"
            )
