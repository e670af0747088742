"""The script port on 30003 and the control script ur-rtde uploads, emulated in Python.

The script's register handshake: the command in ``input_int_register_0``
(arguments in ``input_double_register_0..``, the async flag in
``input_int_register_1``), the status in ``output_int_register_0`` (1 ready,
2 done), bit 1 of ``robot_status_bits`` while the program runs, async
progress in ``output_int_register_2``. And its RTDE watchdog
(``setWatchdog``: ``rtde_set_watchdog("input_int_register_0", f, "stop")``):
with no data package carrying that register for 1/f s the program stops and
the arm decelerates.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import math
import socket
import threading
from collections.abc import Callable
from typing import Any

import numpy as np

from common.clocks.clock import now_s
from robot_side.arm.sim.commands import (
    CMD_JOG_START,
    CMD_JOG_STOP,
    CMD_MOVEJ,
    CMD_MOVEL,
    CMD_NONE,
    CMD_SERVO_STOP,
    CMD_SERVOL,
    CMD_SET_WATCHDOG,
    CMD_SPEED_STOP,
    CMD_SPEEDL,
    CMD_STOP_SCRIPT,
    CMD_STOPJ,
    CMD_STOPL,
    REALTIME_CMDS,
    STATUS_DONE,
    STATUS_READY,
    STATUS_RECEIVED,
    WATCHDOG_VARIABLE,
    CommandLog,
)
from robot_side.arm.sim.controller import SAFETY_MODE_NORMAL, Controller

log = logging.getLogger(__name__)
wire_log = logging.getLogger("robot_side.arm.sim.wire")


def split_programs(buf: bytes) -> tuple[list[str], bytes]:
    """The whole programs in ``buf`` (each from its ``def``/``sec`` line to its top-level
    ``end``), and what is left of it: a program starts once its ``end`` has arrived."""
    programs: list[str] = []
    while True:
        lines = buf.decode(errors="replace").split("\n")
        started = None
        for i, line in enumerate(lines[:-1]):
            if started is None and (line.startswith("def ") or line.startswith("sec ")):
                started = i
            elif started is not None and line.rstrip() == "end":
                programs.append("\n".join(lines[started : i + 1]))
                buf = "\n".join(lines[i + 1 :]).encode()
                break
        else:
            return programs, buf


class ControlScript:
    """The program the controller runs: its registers, its handshake and its watchdog.

    Its methods are called with the controller's ``lock`` held (the tick, the
    RTDE reader, the dashboard), except ``serve``, which takes it itself.
    """

    def __init__(self, controller: Controller, quit: threading.Event) -> None:
        self.controller = controller
        self.config = controller.config
        self._quit = quit
        #: the RTDE input registers, as the last data package of each recipe set them
        self.inputs: dict[str, Any] = {}
        self.out_int: dict[int, int] = {}
        self.out_double: dict[int, float] = {}
        self.program_running = False
        self.scripts_received = 0
        self._executing = False
        #: a fault: the script stopped reading commands and never says "ready" again (a
        #: program stuck in a blocking call), while it still runs until its watchdog trips
        self.hung = False
        self._pending_done = False  # a synchronous motion must finish before "done"
        self._start_at: float | None = None
        self._async_op_id = 0
        self._async_wr_count = 0
        self._async_running = False
        self._last_cmd = 0
        self._realtime_unrun = False  # a realtime command arrived that no cycle has run yet
        #: a new command no cycle has read yet: a client that waits for its reply is silent
        #: because this controller is late (a real one reads it within 2 ms), not counted
        self._unseen_command = False
        self.commands_seen: list[int] = []  # every new command value, for tests
        self.command_log = CommandLog()  # when each command was read, run and answered
        #: the RTDE watchdog: the minimum update frequency, None when off
        self.watchdog_hz: float | None = None
        #: controller time since the last package carrying the variable (stalls not counted)
        self.watchdog_silent_s = 0.0
        #: when the last update of the watchdog's input was applied (monotonic s): a tick
        #: counts the silence since then, not since the tick before it
        self.watchdog_update_s = 0.0
        self.watchdog_trips = 0
        #: when it last tripped (monotonic s, the machine's clock), None before the first
        self.watchdog_tripped_at_s: float | None = None
        #: (monotonic s, why) of the latest ends of a running program: the controller's own
        #: account of when and why the arm was stopped, for whoever judges a stop from outside
        self.program_ends: collections.deque[tuple[float, str]] = collections.deque(maxlen=16)

    def reset_registers(self) -> None:
        """The output registers as a controller that starts serving has them."""
        self.set_async_progress(-1)
        self.out_int[0] = 0

    # -- the script port ---------------------------------------------------------

    def serve(self, sock: socket.socket, peer: Any) -> None:
        """One client of the script port: every program it uploads starts."""
        buf = b""
        try:
            while not self._quit.is_set():
                chunk = sock.recv(65536)
                if not chunk:
                    break
                programs, buf = split_programs(buf + chunk)
                for program in programs:
                    self._received(program)
        except OSError:
            pass
        finally:
            with contextlib.suppress(OSError):
                sock.close()

    def _received(self, program: str) -> None:
        first = program.split("\n", 1)[0]
        wire_log.debug("script <- %d bytes, %s", len(program), first)
        with self.controller.lock:
            self.scripts_received += 1
            if self.program_running:  # a new program aborts the running one: the arm stops
                self.controller.arm.stop(self.config.program_stop_deceleration_m_s2)
                self.program_ends.append((now_s(), "a new program"))
            self.program_running = False
            self.watchdog_hz = None  # a new program replaces the old one and its watchdogs
            self._start_at = now_s() + self.config.script_start_delay_s

    # -- its registers ---------------------------------------------------------------

    def write_inputs(self, names: list[str], values: list[Any]) -> None:
        """An RTDE data package's inputs arrived: an update of the watchdog's variable (whatever
        its value), and a new command when ``input_int_register_0`` changed.

        A realtime command no cycle has run yet runs before a package overwrites it: a
        controller's 500 Hz loop would have read it (the driver sends nothing within 10 ms of a
        command), but a busy machine starves this one for longer.
        """
        # every kick and jog comes through here: the command's value found, not a dict built
        new_cmd = values[names.index(WATCHDOG_VARIABLE)] if WATCHDOG_VARIABLE in names else None
        if self._realtime_unrun and new_cmd not in (None, self._last_cmd) and self.program_running:
            self._run_command(int(self._last_cmd))  # the realtime command still in the register
        for n, v in zip(names, values, strict=True):
            self.inputs[n] = v
        if WATCHDOG_VARIABLE in names:  # an update, whether or not the value changed
            self.watchdog_silent_s = 0.0
            self.watchdog_update_s = now_s()
            self._realtime_unrun = self.program_running and new_cmd in REALTIME_CMDS
        cmd = self.inputs.get("input_int_register_0", 0)
        if cmd != self._last_cmd or (new_cmd in REALTIME_CMDS and self.program_running):
            self.command_log.arrived(int(cmd), self._vec(0) if cmd == CMD_SPEEDL else None)
        if cmd != self._last_cmd:
            args = dict(zip(names, values, strict=True))
            wire_log.debug("RTDE <- command %d %s", cmd, args)
            self._last_cmd = cmd
            self.commands_seen.append(cmd)
            self._unseen_command = True

    def client_may_send(self) -> None:
        """A package told the client the script is ready: its watchdog window starts now.

        ur-rtde sends no command, kick included, before it reads "ready" (its
        ``sendCommand`` spins on this register); a controller publishes that
        within a cycle of clearing the last command, and the client's silence
        before it is the controller's own. Here a starved cycle or sender can
        publish it 100 ms late, and counting that wait tripped the watchdog of a
        driver that kicked as soon as it could (the driver saw no silence).
        """
        if self.watchdog_hz is not None:
            self.watchdog_silent_s = 0.0
            self.watchdog_update_s = now_s()

    # -- the program ---------------------------------------------------------------

    def halt(self) -> None:
        """The program no longer runs, and its watchdog goes with it (the arm is the caller's)."""
        self.program_running = False
        self.watchdog_hz = None
        self.out_int[0] = 0

    def stop_program(self, why: str) -> None:
        """The program ends: the arm decelerates and, as URScript says, its watchdogs go."""
        if self.program_running:
            self.program_ends.append((now_s(), why))
        self.halt()
        self.controller.arm.stop(self.config.program_stop_deceleration_m_s2)
        log.info("control script stopped: %s", why)

    def judge_watchdog(
        self,
        tick_s: float,
        excused: Callable[[], bool],
        at_most_s: float = math.inf,
        describe: Callable[[], str] = str,
    ) -> None:
        """``rtde_set_watchdog(..., "stop")``: no update for 1/f s stops the program.

        ``tick_s`` more of silence, the whole counted no longer than ``at_most_s``;
        none while ``excused`` says the silence is the simulator's own lag (an update
        not yet applied, a state owed to the client); ``describe``: for the trip's log.
        """
        if self.watchdog_hz is None or not self.program_running or self._unseen_command:
            return  # off, or the client waits for this controller to read its command
        self.watchdog_silent_s = min(self.watchdog_silent_s + tick_s, max(0.0, at_most_s))
        silent = self.watchdog_silent_s
        if silent <= 1.0 / self.watchdog_hz or excused():
            return
        self.watchdog_trips += 1
        self.watchdog_tripped_at_s = now_s()
        log.warning(
            "RTDE watchdog: no update of %s for %.0f ms (minimum %.3g Hz; %s)",
            WATCHDOG_VARIABLE,
            silent * 1000,
            self.watchdog_hz,
            describe(),
        )
        self.stop_program("the RTDE input watchdog tripped")

    def cycle(self) -> None:
        """One turn of the script's loop: start an uploaded program, run the command."""
        self._unseen_command = False
        if self._start_at is not None and now_s() >= self._start_at:
            self._start_at = None
            self.program_running = True
            self.hung = False  # a fresh program reads its commands again
            self._executing = False
            self.out_int[0] = STATUS_READY
            log.info("control script running")
        if not self.program_running:
            return
        if self.hung:
            self.out_int[0] = STATUS_RECEIVED
            return
        cmd = int(self.inputs.get("input_int_register_0", 0))
        if cmd == CMD_NONE:
            self._executing = False
            self._pending_done = False
            self.out_int[0] = STATUS_READY
        elif cmd in REALTIME_CMDS:
            self._realtime_unrun = False
            self._run_command(cmd)
            self.out_int[0] = STATUS_READY
        elif not self._executing:
            self._executing = True
            self.out_int[0] = STATUS_RECEIVED
            if self._run_command(cmd):
                self.out_int[0] = STATUS_DONE
                self.command_log.done(cmd)
            else:
                self._pending_done = True

    def after_step(self) -> None:
        """A motion the script waits on has ended: "done", or the async progress cleared."""
        arm = self.controller.arm
        if self._pending_done and not arm.moving:
            self._pending_done = False
            self.out_int[0] = STATUS_DONE
            self.command_log.done(int(self._last_cmd))
        if self._async_running and not arm.moving:
            self._async_running = False
            self.set_async_progress(-1)

    def _f(self, i: int) -> float:
        return float(self.inputs.get(f"input_double_register_{i}", 0.0))

    def _vec(self, start: int) -> np.ndarray:
        return np.array([self._f(start + i) for i in range(6)])

    def _run_command(self, cmd: int) -> bool:
        """Apply ``cmd``; True when it is done, False when "done" waits for the motion."""
        self.command_log.ran(cmd)
        if self.controller.safety_mode != SAFETY_MODE_NORMAL and cmd not in (CMD_STOP_SCRIPT,):
            return True
        arm = self.controller.arm
        is_async = int(self.inputs.get("input_int_register_1", 0)) == 1
        if cmd == CMD_MOVEL:
            arm.move_l(self._vec(0), self._f(6), self._f(7))
            return self._motion_started(is_async)
        if cmd == CMD_MOVEJ:
            arm.move_j(self._vec(0), self._f(6), self._f(7))
            return self._motion_started(is_async)
        if cmd == CMD_SPEEDL:
            arm.speed_l(self._vec(0), self._f(6))
            return True
        if cmd == CMD_SERVOL:
            arm.servo_l(self._vec(0), self._f(8), self._f(9))
            return True
        if cmd in (CMD_SPEED_STOP, CMD_SERVO_STOP, CMD_STOPL, CMD_STOPJ, CMD_JOG_STOP):
            decel = self._f(0) if cmd != CMD_JOG_STOP else 1.2
            arm.stop(decel if decel > 0 else 10.0)
            return is_async or not arm.moving or self._motion_started(False)
        if cmd == CMD_JOG_START:
            speeds = self._vec(0)
            feature = round(self._f(6))
            acc = self._f(7) or 0.5
            if feature == 1:  # tool frame: rotate the twist into the base frame
                r = arm.rot
                speeds = np.concatenate([r @ speeds[:3], r @ speeds[3:]])
            arm.speed_l(speeds, acc)
            return True
        if cmd == CMD_STOP_SCRIPT:
            self.stop_program("stopScript from the client")
            return True
        if cmd == CMD_SET_WATCHDOG:
            hz = self._f(0)
            if hz <= 0:
                log.warning("rtde_set_watchdog with %.3g Hz is not simulated: ignored", hz)
                return True
            self.watchdog_hz, self.watchdog_silent_s = hz, 0.0
            self.watchdog_update_s = now_s()
            log.info("RTDE watchdog on %s at %.3g Hz", WATCHDOG_VARIABLE, hz)
            return True
        if cmd in (47, 48):  # isSteady (numbering differs between ur-rtde versions)
            self.out_int[1] = 0 if arm.moving else 1
            return True
        log.warning("control script command %d is not simulated: acknowledged, no effect", cmd)
        return True

    def _motion_started(self, is_async: bool) -> bool:
        arm = self.controller.arm
        if is_async:
            self._async_running = arm.moving
            self.set_async_progress(0 if arm.moving else -1)
            return True
        return not arm.moving

    def set_async_progress(self, value: int) -> None:
        """output_int_register_2 as the script writes it: op id, write count, running bit."""
        self._async_wr_count = (self._async_wr_count + 1) % 128
        if value == 0:
            self._async_op_id = (self._async_op_id + 1) % 128
        reg = self._async_wr_count * 65536 + self._async_op_id * 16777216
        if value >= 0:
            reg += value + 32768
        self.out_int[2] = reg
