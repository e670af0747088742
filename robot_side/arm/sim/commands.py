"""The control script's commands as the UR simulator reads them, and its account of them.

The numbers are ur-rtde's ``RobotCommand`` numbering, as it writes them to
``input_int_register_0``; ``CommandLog`` is when the controller read each,
first acted on it and answered one its client waits for, which a test prints
when a stop came late (was it read late, or acted on late?).
"""

from __future__ import annotations

import collections

import numpy as np

from common.clocks.clock import now_s

CMD_NONE = 0
CMD_MOVEJ = 1
CMD_MOVEL = 3
CMD_SPEEDJ = 9
CMD_SPEEDL = 10
CMD_SERVOJ = 11
CMD_SPEED_STOP = 15
CMD_SERVO_STOP = 16
CMD_SERVOL = 24
CMD_STOPL = 33
CMD_STOPJ = 34
CMD_SET_WATCHDOG = 35
CMD_JOG_START = 41
CMD_JOG_STOP = 42
CMD_STOP_SCRIPT = 255
#: What a test prints for them (0: no command, which a kick and a clear write).
COMMAND_NAMES = {
    CMD_NONE: "clear or kick",
    CMD_MOVEJ: "moveJ",
    CMD_MOVEL: "moveL",
    CMD_SPEEDJ: "speedJ",
    CMD_SPEEDL: "speedL",
    CMD_SERVOJ: "servoJ",
    CMD_SPEED_STOP: "speedStop",
    CMD_SERVO_STOP: "servoStop",
    CMD_SERVOL: "servoL",
    CMD_STOPL: "stopL",
    CMD_STOPJ: "stopJ",
    CMD_SET_WATCHDOG: "setWatchdog",
    CMD_JOG_START: "jogStart",
    CMD_JOG_STOP: "jogStop",
    CMD_STOP_SCRIPT: "stopScript",
}
#: Commands the script executes every loop and acknowledges with "ready" at once.
REALTIME_CMDS = frozenset({6, 9, 10, 11, 24, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71})

#: The input ur-rtde's script watches (``reg_offset_int`` 0, the only offset simulated).
WATCHDOG_VARIABLE = "input_int_register_0"

STATUS_RECEIVED = 0
STATUS_READY = 1
STATUS_DONE = 2


class CommandLog:
    """(monotonic s, command, "arrived ..." | "ran" | "done") of the latest commands."""

    def __init__(self, size: int = 256) -> None:
        self.events: collections.deque[tuple[float, int, str]] = collections.deque(maxlen=size)
        self._ran = True  # the latest command's first run is noted

    def arrived(self, cmd: int, velocity: np.ndarray | None = None) -> None:
        """A new command, or a realtime one's next package (a jog's next speedL, its speedL to
        rest), with a speed command's linear speed."""
        what = "arrived"
        if velocity is not None:
            what += f" at {float(np.linalg.norm(velocity[:3])):.3f} m/s"
        self.events.append((now_s(), cmd, what))
        self._ran = False

    def ran(self, cmd: int) -> None:
        """Noted once per arrival: a realtime command runs on every cycle."""
        if not self._ran:
            self._ran = True
            self.events.append((now_s(), cmd, "ran"))

    def done(self, cmd: int) -> None:
        self.events.append((now_s(), cmd, "done"))

    def since(self, t_s: float) -> list[tuple[float, int, str]]:
        return [e for e in self.events if e[0] >= t_s]
