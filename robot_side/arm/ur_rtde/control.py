"""The control connection (RTDEControlInterface) and the control script at its other end.

Control calls that wait for the script's "done" (speedStop, stopL, moveL,
stopScript) retry a vanished controller forever, and realtime ones (speedL)
report success into the void. So each call first checks ``isConnected()``
and then runs on a worker thread with a deadline (ur-rtde releases the GIL
in those calls): a stuck call becomes a ``DeviceTimeoutError`` and the line
is marked unusable, never a hang.

One call is on the wire at a time (``wire``): the controller's watchdog is
kicked through the same command register, and a kick between a command and
the script's answer would overwrite the command (``keep_alive``). Every
write is noted, so a silence the watchdog could trip on is logged and a
trip's warning can say what the controller heard last.
"""

from __future__ import annotations

import concurrent.futures
import logging
import queue
import threading
from collections.abc import Callable
from typing import Any

from common.clocks.clock import now_s
from common.devices.lifecycle import at_niceness
from common.errors import DeviceError, DeviceNotConnectedError, DeviceTimeoutError
from common.process.realtime import fair_while
from common.process.spin_guard import SpinGuard
from robot_side.arm.base import SAFETY_THREAD_NICE
from robot_side.arm.ur_rtde.config import URArmConfig
from robot_side.arm.ur_rtde.control_receiver import ControlReceiver
from robot_side.arm.ur_rtde.receive import ReceiveSide

log = logging.getLogger(__name__)


class ArmCommandRefusedError(DeviceError):
    """The controller refused a command (script not running, protective stop, ...)."""


class ControlWorker:
    """One daemon thread running control calls in order.

    Not a ThreadPoolExecutor: its threads are joined at interpreter exit, so a
    call stuck in ur-rtde's reconnect loop would hang the process at exit.
    """

    def __init__(self, name: str) -> None:
        self._jobs: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._thread = threading.Thread(
            target=at_niceness(SAFETY_THREAD_NICE, self._run), name=name, daemon=True
        )
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


#: packages after a command's end before the script is surely ready again: the controller
#: reads the clear in its next cycle and says "ready" in the package after that cycle
READY_AFTER_PACKAGES = 2
#: a kick or a jog (no wait for the script's "done") that has not returned after this spins
#: in ur-rtde for a "ready" that is not coming: its thread goes fair (``SpinGuard``)
SPIN_LIMIT_S = 0.01


class ControlLine:
    """The control interface while connected (``ctrl``), its calls and what went on the wire."""

    def __init__(self, config: URArmConfig, receive: ReceiveSide) -> None:
        self.config = config
        self.receive = receive
        self.ctrl: Any = None
        #: why the interface is unusable (a call stuck inside it); None: usable
        self.broken: str | None = None
        #: why the control script no longer runs (keep_alive noticed it); None: it runs
        self.program_lost: str | None = None
        #: this process is ending the control script itself (disconnect): its stop is no trip
        self.ending_script = False
        #: held by the one call on the wire: a kick must not interrupt a command's handshake
        self.wire = threading.Lock()
        #: controller time the watchdog was armed at; None: nobody counts our silences
        self.watched_since: float | None = None
        self.last_sent = 0.0  # monotonic s: the last write to the command register
        self.last_sent_what = "nothing yet"  # what that write was (a trip's warning names it)
        self.silence_max_s = 0.0  # longest the controller heard nothing from us (watched)
        #: controller time a kick waits for after a command (``script_ready_again``)
        self.ready_at_ts: float | None = None
        self._worker: ControlWorker | None = None
        #: ur-rtde's control thread, real-time while a call waits on it
        self.receiver = ControlReceiver()
        #: kicks and jogs spinning at SCHED_FIFO go fair; the deadman thread checks
        self.spin_guard = SpinGuard(SPIN_LIMIT_S)

    def open(self, ctrl: Any, receiver: ControlReceiver | None = None) -> None:
        self.ctrl = ctrl
        self.receiver = receiver or ControlReceiver()
        self.broken = self.program_lost = None
        self.ending_script = False
        self._worker = ControlWorker(f"urarm-ctrl-{self.config.host}")

    def close(self) -> Any:
        """No interface from here on; the one that was, for the caller to close."""
        ctrl, self.ctrl = self.ctrl, None
        self.receiver.close()
        self.watched_since = None
        if self._worker is not None:
            self._worker.shutdown()
            self._worker = None
        return ctrl

    def call(
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
        ctrl, worker = self.ctrl, self._worker
        if ctrl is None or worker is None:
            raise DeviceNotConnectedError("arm URArm is not connected: call connect() first")
        if self.broken is not None:
            raise DeviceError(
                f"URArm: control interface unusable ({self.broken}); disconnect() and "
                "connect() again"
            )
        if self.program_lost is not None:
            raise DeviceError(f"URArm: {what} refused: {self.program_lost}")
        # the receive side notices a vanished controller first (its stream of packages stops):
        # a call into a control interface whose controller is gone may crash inside ur-rtde
        # (a segfault once, a realtime speedL at a controller killed mid-jog)
        if not ctrl.isConnected() or not self.receive.recv.isConnected():
            raise DeviceNotConnectedError(
                f"URArm: lost the control connection to {self.config.host} before {what}; "
                "the controller's own stop applies. disconnect() and connect() again"
            )
        timeout = self.config.command_timeout_s + extra_s
        with self.wire:
            self.note_sent(what)
            try:
                if realtime:  # nothing waits on the control thread
                    with self.spin_guard.watched(f"URArm {what}"):
                        return self._unspun_now(what, fn, *args)
                return worker.submit(self._unspun, what, fn, *args).result(timeout=timeout)
            except concurrent.futures.TimeoutError:
                self.broken = f"{what} did not return in {timeout:.1f} s"
                raise DeviceTimeoutError(
                    f"URArm: {what} did not return in {timeout:.1f} s (ur-rtde keeps retrying a "
                    f"controller that went away); check {self.config.host}, then reconnect"
                ) from None
            except RuntimeError as e:
                raise DeviceError(f"URArm: {what} failed: {e}") from e
            finally:
                self.note_sent(f"the end of {what}")  # ur-rtde's clear ends a waiting call
                if not realtime:
                    ts = self.receive.last_timestamp()
                    period = 1.0 / self.config.frequency_hz
                    self.ready_at_ts = (
                        None if ts is None else ts + (READY_AFTER_PACKAGES - 0.5) * period
                    )

    def _unspun(self, what: str, fn: Callable[..., Any], *args: Any) -> Any:
        """``_unspun_now``, with ur-rtde's control thread real-time while the call waits on the
        script's answer it reads (``control_receiver.py``)."""
        with self.receiver.realtime():
            return self._unspun_now(what, fn, *args)

    def _unspun_now(self, what: str, fn: Callable[..., Any], *args: Any) -> Any:
        """``fn(*args)`` on this thread, in the fair scheduler while the script may not be
        ready (``script_ready_again``): every thread of the arm process is real-time."""
        if self.script_ready_again():
            return fn(*args)
        with fair_while(f"URArm {what}"):
            return fn(*args)

    def kick(self, ctrl: Any) -> bool:
        """Kick the controller's watchdog through ``ctrl`` unless a call is on the wire (it
        writes the register itself) or ``ctrl`` is no longer the usable interface; never
        waits, unless for a script not yet ready (``script_ready_again``), and then in the
        fair scheduler."""
        if not ctrl.isConnected():
            # kickWatchdog would start ur-rtde's own reconnect; the node's recovery reconnects
            return False
        with self.spin_guard.watched("URArm's keep-alive kick"):
            return self._unspun("the keep-alive's kick", self._kick, ctrl)

    def _kick(self, ctrl: Any) -> bool:
        if not self.wire.acquire(blocking=False):
            return False
        try:
            if ctrl is not self.ctrl or self.broken is not None:
                return False
            self.note_sent("a kick")
            try:
                ctrl.kickWatchdog()
            except RuntimeError as e:  # the next command finds out and says so
                log.debug("URArm: kickWatchdog failed: %s", e)
            finally:
                # a kick waits for the script's "ready" before it writes: a silence that
                # began before it and ended only with its write is said, as a call's is
                self.note_sent("the end of a kick")
            return True
        finally:
            self.wire.release()

    def script_ready_again(self) -> bool:
        """The controller has streamed packages made after the last command's clear.

        ur-rtde's ``sendCommand`` spins, without sleeping, until the script says it is
        ready, which it says in a package made after it read the clear that ends a
        command. From the keep-alive's real-time thread that spin holds a core until then;
        beside a controller that answered late (a starved simulator), two arm processes
        spinning at SCHED_FIFO took both cores until the kernel's real-time throttling,
        and everything else on the machine stalled for about a second. Until the receive
        stream shows ``READY_AFTER_PACKAGES`` packages past the one that was newest when
        the command ended (16 ms at 125 Hz on a controller that keeps its pace), a kick
        goes from the fair scheduler; withheld instead, kicks waited for a receive stream
        starved beside busy loops, and the watchdog tripped.
        """
        due = self.ready_at_ts
        if due is None:
            return True
        ts = self.receive.last_timestamp()
        if ts is None or ts < due:
            return False
        self.ready_at_ts = None
        return True

    def note_sent(self, what: str) -> None:
        """A write to the command register left: the controller's watchdog heard from us.

        A silence over half the watchdog window is logged: the next one may trip it.
        """
        now = now_s()
        silence = now - self.last_sent
        if self.watched_since is not None:
            self.silence_max_s = max(self.silence_max_s, silence)
            if silence > 0.5 * self.config.watchdog_window_s:
                log.warning(
                    "URArm: the controller heard nothing from this process for %.0f ms before "
                    "%s (its watchdog stops the arm at %.0f ms): this process or the machine "
                    "is overloaded",
                    silence * 1000,
                    what,
                    self.config.watchdog_window_s * 1000,
                )
        self.last_sent, self.last_sent_what = now, what

    def program_running(self) -> bool | str:
        """What the control interface says of its script, for an error message."""
        try:
            return bool(self.ctrl.isProgramRunning())
        except Exception:  # only used to word an error message
            return "unknown"
