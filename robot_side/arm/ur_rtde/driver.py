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

That deadman lives in this process, so the controller must also stop the arm
when this process cannot (``kill -9``, ``SIGSTOP``, a wedged interpreter):
``connect`` arms ur-rtde's watchdog (``setWatchdog``: the control script calls
``rtde_set_watchdog("input_int_register_0", 1 / watchdog_window_s, "stop")``)
and a keep-alive thread of its own kicks it every deadman period
(``kickWatchdog`` writes 0 to that register; any command does too), while
the deadman thread is responsive. When no update arrives for
``watchdog_window_s`` the controller stops the program, and the arm with it.
A script that stopped while the safety mode stayed normal (that trip, or a
stop on the pendant) makes the driver refuse every command and ask for a
reconnect, which uploads a fresh script with a cleared command register:
nothing sent before the stop can move the arm after it. docs/arm.md has the
stop budget.

No kick may interrupt a command's handshake (it would overwrite the command
register), so a stop never waits for the deceleration on the wire: a jog is
stopped by a realtime ``speedL`` to zero at the stop's deceleration (no
handshake) and, once the receive stream shows the arm at rest, ``speedStop``
ends the script's speed thread (a handshake of a few controller cycles); a
move by an asynchronous ``stopL``. The kicks go on while the arm decelerates.
"""

from __future__ import annotations

import concurrent.futures
import ctypes
import gc
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
from common.devices import at_niceness, native_threads_at
from common.errors import (
    ConfigError,
    DeviceAlreadyConnectedError,
    DeviceError,
    DeviceNotConnectedError,
    DeviceTimeoutError,
    StaleDataError,
)
from common.logs import BurstLog
from common.messages import ARM_SAFETY_MODES
from common.preflight import Finding, PreflightContext, tcp_findings, tcp_probe
from robot_side.arm.base import (
    NATIVE_DRIVER_THREAD_NICE,
    SAFETY_THREAD_NICE,
    TELEMETRY_POSE_KEYS,
    Arm,
    ArmLimits,
)

log = logging.getLogger(__name__)

#: What the receive interface streams: only what this driver reads (less to parse each package).
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

#: how long connect() waits for each controller port to accept before calling ur-rtde
PORT_PROBE_TIMEOUT_S = 1.0

#: How many times connect() uploads the script and arms the watchdog. The controller counts
#: the window from the moment it arms the watchdog, and ur-rtde's next update goes out only
#: once this process has read the script's answer: a process starved that long at connect (a
#: busy robot PC starting its node) lost its script to the watchdog before the first kick.
WATCHDOG_ARM_TRIES = 3

#: A dead node's arm is still within this (docs/arm.md): two watchdog windows (a controller
#: was reported to trip that late, on URSim) must leave time to decelerate inside it.
STOP_BUDGET_S = 0.4

#: A kick writes 0 to the command register. Within one controller cycle (2 ms on an e-Series,
#: 8 ms on a CB3) after a speedL it could overwrite the command before the script read it, so
#: no kick follows a command sooner than this; that command updated the register itself.
KICK_AFTER_COMMAND_S = 0.01
#: a stop must end within this share of the watchdog window, however fast the wrist turned
#: (see _stop_acceleration): where the receive stream cannot be read, the stop's handshake
#: waits for the whole deceleration with no kick (_keep_alive)
STOP_WITHIN_WINDOW = 0.5
#: how long after the deceleration should have ended a stop still waits for the receive stream
#: to show the arm at rest before it sends its handshake anyway
REST_CATCH_UP_S = 0.05

#: How long a refused command waits for the receive stream to show the stopped script.
REFUSAL_CATCH_UP_S = 0.05
#: After a move ends on the control connection, how long move_to waits for the receive stream
#: (another connection, cached by its own thread) to show the arm at rest: on a busy machine
#: its newest package was still from the move's last milliseconds, 23 um short of the target.
MOVE_CATCH_UP_S = 0.1
AT_REST_M_S = 1e-4
AT_REST_RAD_S = 1e-3


class _Worker:
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


def _retire(interface: Any) -> None:
    """Close an ur-rtde interface and never run its destructor.

    ``disconnect()`` releases the GIL while it sleeps its 0.5 s; the
    destructor sleeps another 0.5 s *holding* it (measured: every other
    thread of the process stops, so a reconnect froze the node's frame loop
    for a second). The object keeps one reference forever: it is never
    destroyed, not even at interpreter exit (where a list of them would cost
    0.5 s each). Closed, it holds no socket and no thread; its memory did not
    show in the process's peak RSS over repeated reconnects.
    """
    try:
        interface.disconnect()
    except RuntimeError as e:  # already gone: nothing left to close
        log.debug("URArm: disconnect of a retired interface: %s", e)
    ctypes.pythonapi.Py_IncRef(ctypes.py_object(interface))


def _retire_side_by_side(*interfaces: Any) -> None:
    """``_retire`` each interface on a thread of its own, and wait for all of them.

    Each ``disconnect()`` closes its sockets and then sleeps 0.5 s with the GIL
    released, so two retired one after the other cost a second where side by
    side they cost half: a node's stop, and a reconnect, are 0.5 s sooner. The
    controller still sees both connections close 0.5 s before either returns.
    """
    started = []
    for interface in interfaces:
        thread = threading.Thread(target=_retire, args=(interface,), name="urarm-retire")
        try:
            thread.start()
        except RuntimeError:  # no new thread at interpreter shutdown: here, in turn
            _retire(interface)
            continue
        started.append(thread)
    for thread in started:
        thread.join()


class WatchdogArmingLostError(DeviceNotConnectedError):
    """The control script stopped while connect() armed its watchdog; connecting again may work."""


class ArmCommandRefusedError(DeviceError):
    """The controller refused a command (script not running, protective stop, ...)."""


#: A controller frees the previous session's RTDE inputs when it sees the
#: close; a reconnect right after a disconnect can arrive first.
CONTROL_CONNECT_TRIES = 5
CONTROL_CONNECT_RETRY_S = 0.2


@dataclass
class URArmConfig:
    host: str = param("192.168.1.10", "the UR controller's IP (pendant: Settings > Network)")
    frequency_hz: float = param(
        125.0,
        "RTDE rate of both interfaces (the state stream, the control script's replies); the "
        "e-Series streams up to 500 Hz, and nothing here reads faster than the 120 Hz frame loop",
    )
    stale_after_s: float = param(
        0.1, "a controller timestamp frozen this long means it stopped streaming: reads raise"
    )
    command_timeout_s: float = param(
        2.0, "a control call still busy after this (plus any deceleration) is abandoned"
    )
    watchdog_window_s: float = param(
        0.15,
        "ur-rtde's watchdog (setWatchdog at 1/window Hz): the controller stops the program and "
        "the arm when this process sends nothing this long (kill -9, SIGSTOP); kicked every "
        "20 ms, so a kick may come 130 ms late before it trips",
    )
    limits: ArmLimits = param(ArmLimits(), "workspace box, speed caps and the jog deadman")
    own_process: bool = param(
        True,
        "run the driver (the watchdog's keep-alive, the jog deadman, stops, the pose read "
        "back) in a process of its own, its keep-alive real-time where the unit grants it "
        "(docs/arm.md); false = inside the robot node, sharing its interpreter lock",
    )
    realtime_priority: int = param(
        20,
        "SCHED_FIFO priority of the keep-alive and deadman threads in the arm process where "
        "granted (the unit's LimitRTPRIO=, or root); refused: the highest niceness allowed. "
        "0 = never real-time",
    )


class URArm(Arm):
    Config = URArmConfig

    def __init__(self, config: URArmConfig | None = None) -> None:
        self.config = config or URArmConfig()
        super().__init__(self.config.limits)
        self._check_watchdog_config()
        self._recv: Any = None
        self._ctrl: Any = None
        self._worker: _Worker | None = None
        self._ctrl_broken: str | None = None
        self._speeding = False
        self._moving = False
        self._move_ended_at: float | None = None  # when the control connection said so
        self._last_ts = -1.0
        self._last_ts_change = 0.0
        self._stale_events = 0
        self._live_ts, self._live_ts_change = -1.0, 0.0  # live_readings' own view of the stream
        # one control call on the wire at a time: a kick between a command and the script's
        # answer would overwrite the command register (see _keep_alive)
        self._wire = threading.Lock()
        self._watchdog_armed_ts: float | None = None  # controller time it was armed at
        self._last_sent = 0.0  # monotonic s: the last write to the command register
        self._last_sent_what = "nothing yet"  # what that write was (a trip's warning names it)
        self._keep_alive_ran = (0.0, 0.0)  # monotonic s: the keep-alive thread's last two turns
        self._silence_max_s = 0.0  # longest the controller heard nothing from us (connected)
        self._kicks = 0
        self._kicks_withheld = BurstLog(log, "URArm")
        self._program_lost: str | None = None

    def _check_watchdog_config(self) -> None:
        window, lim = self.config.watchdog_window_s, self.limits
        if not window > 0:
            raise ConfigError(
                "arm watchdog_window_s must be positive: the watchdog cannot be turned off"
            )
        if 2 * window >= STOP_BUDGET_S:
            raise ConfigError(
                f"arm watchdog_window_s {window:g}: a controller that trips as late as two "
                f"windows would leave no time to decelerate within the {STOP_BUDGET_S * 1000:.0f}"
                " ms a dead node may leave the arm moving (docs/arm.md); shorten it"
            )
        if window < 3 * self.deadman_period_s:
            raise ConfigError(
                f"arm watchdog_window_s {window:g} is less than three kicks "
                f"({self.deadman_period_s * 1000:.0f} ms apart): one late thread would stop "
                "the program; lengthen it"
            )
        # a stop waits for the script's answer and no kick may interrupt it (_keep_alive)
        decel_s = lim.max_linear_speed_m_s / lim.stop_deceleration_m_s2
        if decel_s >= window:
            raise ConfigError(
                f"arm stop_deceleration_m_s2 {lim.stop_deceleration_m_s2:g} takes "
                f"{decel_s * 1000:.0f} ms from the speed cap, as long as the watchdog window "
                f"({window * 1000:.0f} ms): a stop sends nothing while it waits for the script, "
                "so the watchdog would trip on our own stops. Raise the deceleration"
            )
        if decel_s > window / 2:
            log.warning(
                "URArm: a stop from the %.2f m/s cap takes %.0f ms, over half the %.0f ms "
                "watchdog window: on a loaded machine the watchdog may trip during a stop "
                "(the arm stops either way); raise stop_deceleration_m_s2",
                lim.max_linear_speed_m_s,
                decel_s * 1000,
                window * 1000,
            )

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
        """Either interface lost the controller, the control interface was abandoned, or the
        control script stopped under us.

        ur-rtde never brings a lost receive interface back, and its control interface's own
        reconnect gives up after one try while the controller is away, so a controller that
        rebooted or got its cable back is only used again through ``disconnect()`` and
        ``connect()`` (the node's ``DeviceRecovery`` does that off the frame loop).
        """
        if self._ctrl_broken is not None or self._program_lost is not None:
            return True
        recv, ctrl = self._recv, self._ctrl
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
        import rtde_control
        import rtde_receive

        host = self.config.host
        hint = (
            f"check that the UR controller at {host} is on, reachable (ping it), in remote "
            "control, and that no other program holds its RTDE inputs"
        )
        self._require_ports_open(hint)
        try:
            recv = native_threads_at(
                NATIVE_DRIVER_THREAD_NICE,
                lambda: rtde_receive.RTDEReceiveInterface(
                    host, self.config.frequency_hz, RECEIVE_VARIABLES
                ),
            )
        except RuntimeError as e:
            msg = f"URArm: RTDE receive to {host} failed ({e}); {hint}"
            raise DeviceNotConnectedError(msg) from e
        ctrl = None
        for attempt in range(CONTROL_CONNECT_TRIES):
            try:
                ctrl = native_threads_at(
                    NATIVE_DRIVER_THREAD_NICE,
                    lambda: rtde_control.RTDEControlInterface(host, self.config.frequency_hz),
                )
                break
            except RuntimeError as e:
                # Right after a disconnect the controller may still hold our previous
                # session's input registers; they are freed when it sees the close.
                if "already in use" in str(e) and attempt + 1 < CONTROL_CONNECT_TRIES:
                    log.info("URArm: RTDE inputs at %s still held; trying again", host)
                    if attempt == 0:
                        # an exception's traceback can keep our previous interface alive in
                        # cyclic garbage, and only its destructor closes the connection
                        gc.collect()
                    time.sleep(CONTROL_CONNECT_RETRY_S)
                    continue
                _retire(recv)
                msg = f"URArm: RTDE control to {host} failed ({e}); {hint}"
                raise DeviceNotConnectedError(msg) from e
        self._recv, self._ctrl = recv, ctrl
        self._ctrl_broken = self._program_lost = None
        self._speeding = self._moving = False
        self._worker = _Worker(f"urarm-ctrl-{host}")
        self._last_ts = recv.getTimestamp()
        self._last_ts_change = now_s()
        # the kicking thread first: started after the watchdog, its start-up in a busy
        # process was once longer than the window ("0 kicks", a trip at every connect)
        self._start_deadman()
        self._arm_watchdog()
        log.info(
            "URArm connected to %s (watchdog %.0f ms)", host, self.config.watchdog_window_s * 1000
        )

    def _require_ports_open(self, hint: str) -> None:
        """Refuse at once when a controller port does not accept a connection.

        ur-rtde's constructors hold the GIL while they connect: against a
        controller that is still booting, or behind a pulled cable (no answer at
        all), every thread of the node would stop until their timeouts. A plain
        socket waits without the GIL, so a reconnect that cannot work yet costs
        the frame loop nothing.
        """
        for port in CONTROLLER_PORTS:
            problem = tcp_probe(self.config.host, port, PORT_PROBE_TIMEOUT_S)
            if problem is not None:
                raise DeviceNotConnectedError(f"URArm: {problem}; {hint}")

    def _arm_watchdog(self) -> None:
        """From here on the controller stops the arm whenever this process falls silent."""
        self._silence_max_s, self._kicks = 0.0, 0
        try:
            hz = 1.0 / self.config.watchdog_window_s
            ok = self._control("setWatchdog", self._ctrl.setWatchdog, hz)
            self._check(ok, "setWatchdog")
        except DeviceError as e:
            lost = self._program_lost
            self.disconnect()
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
        self._watchdog_armed_ts = float(self._recv.getTimestamp())
        # from here on a late kick can stop the arm: the keep-alive's timing counts from now
        self.keep_alive_periods.clear()

    def disconnect(self) -> None:
        """Stop the arm, end the control script, close both interfaces, whatever fails."""
        if not self.is_connected:
            return
        self._stop_deadman()
        recv, ctrl = self._recv, self._ctrl
        try:
            with self._lock:
                # once the script is known to have stopped there is nothing left to tell it
                if self._program_lost is None:
                    try:
                        self._stop_locked()
                    except DeviceError as e:
                        log.warning("URArm: stop on disconnect failed: %s", e)
                if self._program_lost is None:
                    try:
                        self._control("stopScript", ctrl.stopScript)
                    except DeviceError as e:
                        log.warning("URArm: stopScript on disconnect failed: %s", e)
        finally:
            self._watchdog_armed_ts = None
            self._recv = self._ctrl = None
            if self._worker is not None:
                self._worker.shutdown()
                self._worker = None
            if self._ctrl_broken is not None:
                # a call is stuck inside it; destroying it now would block on that call
                log.warning("URArm: control interface abandoned: %s", self._ctrl_broken)
                _ABANDONED.append(ctrl)
                _retire(recv)
            else:
                _retire_side_by_side(ctrl, recv)
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

    def live_readings(self) -> dict[str, float]:
        """The receive interface's newest TCP pose and speed, read from its cache.

        ur-rtde's receive thread fills that cache from its own connection, so
        this never waits for the control side (a stop, a move's handshake) or
        the driver's lock; the getters take microseconds. Nothing when the
        stream is lost, stale (``stale_after_s``, judged on this caller's own
        reads) or the program stopped under us.
        """
        recv = self._recv
        if recv is None or self._program_lost is not None:
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
        if self._program_lost is not None:
            raise DeviceError(f"URArm: {what} refused: {self._program_lost}")
        # the receive side notices a vanished controller first (its stream of packages stops):
        # a call into a control interface whose controller is gone may crash inside ur-rtde
        # (a segfault once, a realtime speedL at a controller killed mid-jog)
        if not ctrl.isConnected() or not self._recv.isConnected():
            raise DeviceNotConnectedError(
                f"URArm: lost the control connection to {self.config.host} before {what}; "
                "the controller's own stop applies. disconnect() and connect() again"
            )
        timeout = self.config.command_timeout_s + extra_s
        with self._wire:
            self._note_sent(what)
            try:
                if realtime:
                    return fn(*args)
                return self._worker.submit(fn, *args).result(timeout=timeout)
            except concurrent.futures.TimeoutError:
                self._ctrl_broken = f"{what} did not return in {timeout:.1f} s"
                raise DeviceTimeoutError(
                    f"URArm: {what} did not return in {timeout:.1f} s (ur-rtde keeps retrying a "
                    f"controller that went away); check {self.config.host}, then reconnect"
                ) from None
            except RuntimeError as e:
                raise DeviceError(f"URArm: {what} failed: {e}") from e
            finally:
                self._note_sent(f"the end of {what}")  # ur-rtde's clear ends a waiting call

    # -- the controller's watchdog --------------------------------------------

    def _note_sent(self, what: str) -> None:
        """A write to the command register left: the controller's watchdog heard from us.

        A silence over half the watchdog window is logged: the next one may trip it.
        """
        now = now_s()
        silence = now - self._last_sent
        if self._watchdog_armed_ts is not None:
            self._silence_max_s = max(self._silence_max_s, silence)
            if silence > 0.5 * self.config.watchdog_window_s:
                log.warning(
                    "URArm: the controller heard nothing from this process for %.0f ms before "
                    "%s (its watchdog stops the arm at %.0f ms): this process or the machine "
                    "is overloaded",
                    silence * 1000,
                    what,
                    self.config.watchdog_window_s * 1000,
                )
        self._last_sent, self._last_sent_what = now, what

    def _keep_alive(self) -> None:
        """Kick the watchdog unless a command just did; notice a script that stopped under us.

        Called every deadman period on the keep-alive thread; never waits: a
        kick while another call is on the wire is skipped, since that call
        writes the register itself and a kick in the middle of its handshake
        would overwrite the command before the script read it. No kick while
        the deadman thread is stuck: the kicks also vouch for it.
        """
        self._keep_alive_ran = (self._keep_alive_ran[1], now_s())
        recv, ctrl = self._recv, self._ctrl
        if (
            self._watchdog_armed_ts is None
            or recv is None
            or ctrl is None
            or self._ctrl_broken is not None
            or self._program_lost is not None
        ):
            return
        self._notice_program_stop(recv)
        if self._program_lost is not None or now_s() - self._last_sent < KICK_AFTER_COMMAND_S:
            return
        if not self.deadman_responsive:
            # a deadman that cannot stop a jog must not be covered for: the controller stops it
            self._kicks_withheld(
                f"the deadman thread has not woken for over {self.limits.jog_timeout_s:g} s "
                "(it could not stop a jog): kicks withheld, the controller's watchdog stops the arm"
            )
            return
        if not ctrl.isConnected():
            # kickWatchdog would start ur-rtde's own reconnect; the node's recovery reconnects
            return
        if not self._wire.acquire(blocking=False):
            return
        try:
            if ctrl is not self._ctrl or self._ctrl_broken is not None:
                return
            self._note_sent("a kick")
            try:
                ctrl.kickWatchdog()
            except RuntimeError as e:  # the next command finds out and says so
                log.debug("URArm: kickWatchdog failed: %s", e)
            self._kicks += 1
        finally:
            self._wire.release()

    def _notice_program_stop(self, recv: Any, refused: bool = False) -> None:
        """The control script stopped while the safety mode is normal: a watchdog trip or a stop.

        Seen in the receive stream: every deadman period (only in data sent
        after the script was certainly running), and when ur-rtde ``refused`` a
        command. A protective or emergency stop is left to ``_check_safety``,
        which names it.
        """
        if self._program_lost is not None:
            return
        try:
            if not recv.isConnected():
                return
            armed = self._watchdog_armed_ts
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
        self._program_lost = (
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
            self._program_lost,
            (now - self._last_sent) * 1000,
            self._last_sent_what,
            "holds" if self._wire.locked() else "does not hold",
            (now - self._keep_alive_ran[0]) * 1000,
            (now - self._keep_alive_ran[1]) * 1000,
            self._silence_max_s * 1000,
            self._kicks,
        )

    def _check(self, ok: Any, what: str) -> None:
        if ok is False:
            self._notice_program_stop(self._recv, refused=True)
            if self._program_lost is not None:
                raise DeviceError(f"URArm: {what} refused: {self._program_lost}")
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
            self._jog_acceleration(velocity),
            0.0,
            realtime=True,
        )
        self._check(ok, "speedL")
        self._speeding = True

    def move_to(self, pose: Any, speed: float | None = None, wait: bool = True) -> None:
        """As ``Arm.move_to``; after a watchdog trip it first reconnects (a fresh script).

        A move is an absolute target asked for now, not a velocity that was
        right only when it was sent: a jog after a trip is refused instead, and
        the node's recovery reconnects.
        """
        if self._program_lost is not None:
            log.warning("URArm: reconnecting for a move: %s", self._program_lost)
            self.disconnect()
            self.connect()
        super().move_to(pose, speed, wait)

    def _send_move(self, pose: np.ndarray, speed: float) -> None:
        ctrl = self._ctrl
        self._check_safety("move")
        if self._speeding:
            self._stop_speed()
        self._moving = True
        self._move_ended_at = None
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
        now = now_s()
        if self._move_ended_at is None:
            self._move_ended_at = now
        speed = np.asarray(self._fresh().getActualTCPSpeed(), dtype=float)
        moving = (
            np.linalg.norm(speed[:3]) > AT_REST_M_S or np.linalg.norm(speed[3:]) > AT_REST_RAD_S
        )
        if moving and now - self._move_ended_at < MOVE_CATCH_UP_S:
            return False  # the receive stream has not caught up: the pose read next would lag
        self._moving = False
        self._move_ended_at = None
        return True

    def _decel_time(self) -> float:
        return max(
            self.limits.max_linear_speed_m_s / self.limits.stop_deceleration_m_s2,
            STOP_WITHIN_WINDOW * self.config.watchdog_window_s,
        )

    def _deadman_stop_limit_s(self) -> float:
        """A stop's two calls, each with its deadline and the wait for rest between."""
        return 2 * (self.config.command_timeout_s + self._decel_time() + REST_CATCH_UP_S)

    def _jog_acceleration(self, velocity: np.ndarray) -> float:
        """speedL's one acceleration, which the controller applies to the turn too (rad/s^2).

        URScript's ``speedl(xd, a)``: ``aRot`` defaults to ``a``, and ur-rtde passes no
        ``aRot``. A pure wrist turn therefore ramps at the angular limit; a jog that
        translates at the lower of the two, so neither part exceeds its own.
        """
        lim = self.limits
        if not np.any(velocity[:3]):
            return lim.angular_acceleration_rad_s2
        return min(lim.linear_acceleration_m_s2, lim.angular_acceleration_rad_s2)

    def _stop_acceleration(self) -> float:
        """The stop's one acceleration: the limits' gentle one, or more if the wrist turns fast.

        ur-rtde's stops take one acceleration, and the controller decelerates a rotation at
        the same number in rad/s^2 (URScript ``stopl(a)``: ``aRot`` defaults to ``a``). From
        the 0.5 rad/s cap at 2 rad/s^2 a stop took 250 ms, waiting unkicked on the script:
        the watchdog (150 ms) tripped on every fast wrist turn's stop. A translation keeps its
        gentle stop (a held pipette feels it); a turn stops within half the window.
        """
        try:
            turning = float(np.linalg.norm(self._fresh().getActualTCPSpeed()[3:]))
        except DeviceError:  # cannot see it: assume the cap
            turning = self.limits.max_angular_speed_rad_s
        if not np.isfinite(turning):
            turning = self.limits.max_angular_speed_rad_s
        within = STOP_WITHIN_WINDOW * self.config.watchdog_window_s
        return max(self.limits.stop_deceleration_m_s2, turning / within)

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
        a = self._stop_acceleration()
        ok = self._control("speedL to rest", self._ctrl.speedL, [0.0] * 6, a, 0.0, realtime=True)
        self._check(ok, "speedL to rest")
        self._wait_at_rest()
        ok = self._control("speedStop", self._ctrl.speedStop, a, extra_s=self._decel_time())
        self._speeding = False
        self._check(ok, "speedStop")

    def _stop_move(self) -> None:
        """A move in progress is stopped asynchronously (the wire free for kicks), then awaited."""
        if not self._moving:  # nothing this driver started moves: a short handshake
            self._control("stopL", self._ctrl.stopL, self._stop_acceleration(), False)
            return
        self._control(
            "stopL", self._ctrl.stopL, self._stop_acceleration(), True, extra_s=self._decel_time()
        )
        self._moving = False
        self._wait_at_rest()

    def _wait_at_rest(self) -> None:
        """Until the receive stream shows the TCP at rest, or the deceleration's time is up.

        The wire lock is not held: the keep-alive thread kicks meanwhile. A
        stream that cannot be read ends the wait at once (the handshake that
        follows then waits for the deceleration itself).
        """
        deadline = now_s() + self._decel_time() + REST_CATCH_UP_S
        while not self._seen_at_rest():
            if now_s() >= deadline:
                log.debug("URArm: the arm still moves after the stop's deceleration")
                return
            time.sleep(0.002)

    def _seen_at_rest(self) -> bool:
        """The receive stream shows the TCP still (False when it cannot be read)."""
        try:
            speed = np.asarray(self._fresh().getActualTCPSpeed(), dtype=float)
        except (DeviceError, RuntimeError):
            return False
        return bool(
            np.linalg.norm(speed[:3]) <= AT_REST_M_S and np.linalg.norm(speed[3:]) <= AT_REST_RAD_S
        )

    def _send_stop(self) -> None:
        """A jog's speed thread and a move each stopped as above; a still arm costs no handshake.

        Every handshake is silence on the wire (no kick may interrupt it), so a
        stop of an arm this driver knows to be still (a repeated stop, a
        released key after a STOP) sends nothing, unless the receive stream
        shows the TCP moving or cannot be read: then both stops go.
        """
        if self._program_lost is not None:
            log.debug("URArm: stop: no control script runs; the controller stopped the arm")
            self._speeding = self._moving = False
            return
        unknown = not (self._speeding or self._moving) and not self._seen_at_rest()
        errors = []
        for step in (
            self._stop_speed if self._speeding or unknown else None,
            self._stop_move if self._moving or unknown else None,
        ):
            if step is None:
                continue
            try:
                step()
            except DeviceError as e:
                errors.append(e)
        if errors and self._program_lost is None:  # else the controller stopped the arm
            raise errors[0]

    def telemetry(self) -> dict[str, float]:
        """Adds the controller's TCP speed, safety mode and program state (RTDE cache reads)."""
        if self._program_lost is not None:  # the node's poll then reconnects at once
            raise DeviceError(f"URArm: {self._program_lost}")
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
        out.update(
            host=self.config.host,
            stale_events=self._stale_events,
            watchdog_window_ms=self.config.watchdog_window_s * 1000,
            watchdog_kicks=self._kicks,
            longest_silence_ms=round(self._silence_max_s * 1000, 1),
        )
        if self._program_lost is not None:
            out["program_lost"] = self._program_lost
        if self.is_connected:
            out["safety"] = self._safety_text()
            out["program_running"] = self._program_running()
            out["data_age_ms"] = round((now_s() - self._last_ts_change) * 1000, 1)
            if self._ctrl_broken:
                out["control_broken"] = self._ctrl_broken
        return out
