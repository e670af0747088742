"""A UR e-Series controller on loopback, as far as ur-rtde can tell.

Three TCP servers on one host address, on the controller's fixed ports, each
a part of :class:`URSimulator`:

- ``rtde``: RTDE protocol 2 on 30004 (``rtde_server``).
- ``dashboard``: the dashboard's text commands on 29999 (``dashboard``).
- ``script``: the script port on 30003, and the control script ur-rtde
  uploads, "run" in Python: its register handshake and its RTDE watchdog
  (``script``).

Behind them a :class:`~robot_side.arm.sim.kinematics.KinematicArm` moves the
TCP as moveL/moveJ/speedL/servoL/jog/stop say, on the controller's own
500 Hz cycle, or (``motion_clock = "external"``) only as far as its owner's
:meth:`URSimulator.advance` says: the lab world's simulated time. Because ur-rtde's ports are
fixed, simulators that run side by side each take their own loopback
address (127.0.0.x); ``host="auto"`` picks a free one.

Fault injection for tests and demos: :meth:`URSimulator.freeze` (the
controller stops streaming but keeps the sockets: stale data),
:meth:`URSimulator.protective_stop`, and :meth:`URSimulator.stop` (the
controller vanishes). Set the ``robot_side.arm.sim.wire`` logger to DEBUG to
see every message but the periodic data packages.
"""

from __future__ import annotations

import contextlib
import logging
import random
import socket
import threading
from typing import Any

from common.clocks.clock import Rate, now_s
from common.devices.lifecycle import as_hardware
from common.errors import ConfigError, DeviceError
from robot_side.arm.sim.controller import (
    DASHBOARD_PORT,
    RTDE_PORT,
    SAFETY_MODE_PROTECTIVE_STOP,
    SCRIPT_PORT,
    Controller,
    URSimConfig,
)
from robot_side.arm.sim.dashboard import DashboardServer
from robot_side.arm.sim.kinematics import Mode
from robot_side.arm.sim.rtde_server import RTDEServer
from robot_side.arm.sim.script import ControlScript

__all__ = ["URSimConfig", "URSimulator"]

log = logging.getLogger(__name__)

#: Longest step the kinematics take when the machine stalls the tick thread.
MAX_TICK_S = 0.05

#: The longest a single tick adds to the watchdog's silence while its client is connected.
#: A tick later than this means the simulator itself stalled (a loaded machine, a physics
#: step holding the GIL): a real controller is hard real time and never does, so the stall
#: is not counted against the client, whose answer to a command may be waiting on this very
#: tick. A client that closed its connection (its process died) waits on nothing: its
#: silence counts in full, as on the controller (the arm of a killed arm process ran on for
#: a second when a starved simulator counted 20 ms a tick).
MAX_SILENCE_TICK_S = 0.02


class URSimulator(Controller):
    """The simulated controller; ``start()`` binds and serves, ``stop()`` vanishes.

    Its servers are its parts: ``rtde``, ``dashboard`` and ``script`` (which
    also runs the uploaded program and its watchdog).
    """

    def __init__(self, config: URSimConfig | None = None) -> None:
        super().__init__(config)
        self.host = self.config.host
        self._quit = threading.Event()
        self._frozen = threading.Event()
        self._threads: list[threading.Thread] = []
        self._listeners: list[socket.socket] = []
        self._other_socks: list[socket.socket] = []
        self.script = ControlScript(self, self._quit)
        self.rtde = RTDEServer(self, self.script, self._quit)
        self.dashboard = DashboardServer(self, self.script)

    # -- lifecycle -----------------------------------------------------------

    def start(self) -> URSimulator:
        if self.config.host == "auto":
            self.host = self._bind_free_loopback()
        else:
            self.host = self.config.host
            self._bind_all(self.host)
        self._quit.clear()
        self.script.reset_registers()
        for name, target in (
            ("tick", self._tick_loop),
            ("rtde-accept", lambda: self._accept_loop(self._listeners[0], self.rtde.serve)),
            (
                "dash-accept",
                lambda: self._accept_loop(self._listeners[1], self.dashboard.serve, keep=True),
            ),
            (
                "script-accept",
                lambda: self._accept_loop(self._listeners[2], self.script.serve, keep=True),
            ),
        ):
            self._spawn(f"ursim-{self.host}-{name}", target)
        log.info(
            "UR simulator serving on %s (RTDE %d, dashboard %d, script %d)",
            self.host,
            RTDE_PORT,
            DASHBOARD_PORT,
            SCRIPT_PORT,
        )
        return self

    def stop(self) -> None:
        """Close every socket and thread: to a client the controller has vanished."""
        self._quit.set()
        for s in self._listeners:
            # close() alone does not wake a thread blocked in accept() on Linux
            with contextlib.suppress(OSError):
                s.shutdown(socket.SHUT_RDWR)
            with contextlib.suppress(OSError):
                s.close()
        conns = self.rtde.take_connections()
        with self.lock:
            others, self._other_socks = self._other_socks, []
        for c in conns:
            c.close()
        for s in others:
            with contextlib.suppress(OSError):
                s.shutdown(socket.SHUT_RDWR)
            with contextlib.suppress(OSError):
                s.close()
        for t in self._threads:
            if t is not threading.current_thread():
                t.join(timeout=2.0)
        self._threads.clear()
        self._listeners.clear()
        log.info("UR simulator on %s stopped", self.host)

    def __enter__(self) -> URSimulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _bind_all(self, host: str) -> None:
        socks = []
        try:
            for port in (RTDE_PORT, DASHBOARD_PORT, SCRIPT_PORT):
                s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
                socks.append(s)
                s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                s.bind((host, port))
                s.listen(8)
        except OSError as e:
            for s in socks:
                s.close()
            raise DeviceError(
                f"UR simulator cannot bind {host}:{port} ({e}); another simulator or a "
                "controller uses that address: choose another 127.0.0.x or host='auto'"
            ) from e
        self._listeners = socks

    def _bind_free_loopback(self) -> str:
        candidates = list(range(2, 255))
        random.shuffle(candidates)
        for x in candidates:
            host = f"127.0.0.{x}"
            try:
                self._bind_all(host)
            except DeviceError:
                continue
            return host
        raise DeviceError("UR simulator: no free 127.0.0.x address with ports 29999/30003/30004")

    def _spawn(self, name: str, target: Any) -> None:
        t = threading.Thread(target=as_hardware(target), name=name, daemon=True)
        self._threads.append(t)
        t.start()

    def _accept_loop(self, listener: socket.socket, serve: Any, keep: bool = False) -> None:
        """Each client on a thread of its own; ``keep``: its socket is closed at ``stop``
        (an RTDE server closes its own)."""
        while not self._quit.is_set():
            try:
                sock, peer = listener.accept()
            except OSError:
                return
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            if keep:
                with self.lock:
                    self._other_socks.append(sock)
            threading.Thread(
                target=serve, args=(sock, peer), name=f"ursim-{self.host}-conn", daemon=True
            ).start()

    # -- fault injection -----------------------------------------------------

    def freeze(self, frozen: bool = True) -> None:
        """Stop (or resume) streaming data packages; sockets stay open."""
        if frozen:
            self._frozen.set()
        else:
            self._frozen.clear()

    def hang_script(self, hung: bool = True) -> None:
        """The control script stops reading commands and saying "ready" (or goes on again):
        ur-rtde's next command, a watchdog kick included, waits for a "ready" that does not
        come until its own timeout, while the watchdog stops the program."""
        with self.lock:
            self.script.hung = hung

    def protective_stop(self) -> None:
        """Stop hard and halt the program, as a UR does; a client must restart its script."""
        with self.lock:
            self.safety_mode = SAFETY_MODE_PROTECTIVE_STOP
            self.arm.stop(10.0)
            self.script.halt()

    # -- state seen by tests -------------------------------------------------

    def commands_seen(self) -> list[int]:
        """Every new value of input_int_register_0, in order (0 = cleared)."""
        with self.lock:
            return list(self.script.commands_seen)

    def command_events(self, since_s: float = 0.0) -> list[tuple[float, int, str]]:
        """(monotonic s, command, "arrived" | "ran" | "done") since ``since_s``: when this
        controller read each command, first acted on it and answered a waiting one."""
        with self.lock:
            return self.script.command_log.since(since_s)

    def stats(self) -> dict[str, Any]:
        with self.lock:
            script = self.script
            return {
                "host": self.host,
                "program_running": script.program_running,
                "scripts_received": script.scripts_received,
                "data_packages_sent": self.rtde.data_packages_sent,
                "rtde_clients": self.rtde.client_count(),
                "safety_mode": self.safety_mode,
                "mode": self.arm.mode.value,
                "watchdog_hz": script.watchdog_hz,
                "watchdog_trips": script.watchdog_trips,
                "watchdog_tripped_at_s": script.watchdog_tripped_at_s,
                "program_ends": [list(e) for e in script.program_ends],
            }

    # -- the controller cycle --------------------------------------------------

    def _tick_loop(self) -> None:
        rate = Rate(self.config.tick_hz)
        last = now_s()
        script = self.script
        while not self._quit.is_set():
            # step by the time that really passed: on a loaded machine ticks are missed,
            # and the arm must still move in real time, as the robot would (unless a
            # physics world owns the arm's clock: motion_clock "external", advance())
            t = now_s()
            elapsed, last = t - last, t
            dt = min(elapsed, MAX_TICK_S)
            with self.lock:
                try:
                    if self.config.motion_clock == "wall":
                        # the silence since the last update when one came after the last tick: a
                        # late tick counted the time before the update too, and tripped early
                        silent = max(0.0, min(elapsed, t - script.watchdog_update_s))
                        if silent > MAX_SILENCE_TICK_S and self.rtde.writer_connected():
                            silent = MAX_SILENCE_TICK_S  # our stall, not the client's silence
                        script.judge_watchdog(
                            silent, self._silence_is_ours, describe=self.rtde.writer_summary
                        )
                    script.cycle()
                except Exception:
                    self._runtime_error()
                if dt > 0 and self.config.motion_clock == "wall":
                    self._step_arm(dt)
                    self.clock_s += dt
                script.after_step()
                # a package goes out at each connection's own rate: the state is built only
                # on a tick that sends one, a quarter of them at ur-rtde's 125 Hz (it was
                # the cycle's largest cost)
                due = self.rtde.due()
                state = self.rtde.state() if due and not self._frozen.is_set() else None
            if state is not None:
                for c in due:
                    self.rtde.send(c, state)
            rate.sleep()

    def advance(self, dt_s: float) -> None:
        """Move the arm by ``dt_s`` of its owner's time (``motion_clock = "external"``).

        A physics world calls this with the simulated time it is about to
        step, so the arm and the physics share one clock: a world that falls
        behind real time slows the arm with it instead of seeing it jump.
        The RTDE watchdog counts this time too: the arm a silent client
        leaves moving covers the same distance before it stops, and a stop
        the client waits on (its kicks queued behind it) takes as long on
        this clock as the watchdog allows on it. It never counts more
        silence than the wall time since the last update, though: a world
        that fell behind steps the time it owes at once, and that time
        passed before an update its reader applied meanwhile (a trip at 141
        ms of real silence, the world catching up 50 ms after a kick).
        """
        if self.config.motion_clock != "external":
            raise ConfigError("URSimulator.advance needs motion_clock = 'external'")
        with self.lock:
            while dt_s > 1e-12:
                step = min(dt_s, MAX_TICK_S)
                try:
                    self.script.judge_watchdog(
                        min(step, MAX_SILENCE_TICK_S),
                        self._silence_is_ours,
                        at_most_s=now_s() - self.script.watchdog_update_s,
                        describe=self.rtde.writer_summary,
                    )
                except Exception:
                    self._runtime_error()
                self._step_arm(step)
                dt_s -= step

    def _silence_is_ours(self) -> bool:
        """The client's silence is this simulator's doing, not the client's: an update arrived
        that is not applied yet, or the client waits for a script state this simulator set and
        has not sent (unless its stream is frozen on purpose: then the client hears nothing,
        as behind a held-back network). Call with ``lock`` held."""
        if self.rtde.input_unread():
            return True
        return not self._frozen.is_set() and self.rtde.status_owed()

    def _step_arm(self, dt: float) -> None:
        """One integration step of the arm; call with ``lock`` held."""
        try:
            self.arm.step(dt)
        except Exception:
            self._runtime_error()
        self.note_motion()

    def _runtime_error(self) -> None:
        """A controller stops the program on a runtime error and keeps serving."""
        log.exception("control script runtime error: program stopped")
        self.script.stop_program("runtime error")
        self.arm.velocity[:] = 0.0
        self.arm.mode = Mode.IDLE
