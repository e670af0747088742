"""The demo's child processes, kept running as systemd keeps the units running.

Each child is a :class:`~deploy.units.service.Service` (a catalogue entry with
the run's arguments: its notify socket, its readiness, its watchdog). A child
that exits while the demo runs (a crash, ``kill -9``) is started
again after its unit's ``RestartSec=`` (``deploy/systemd/deepxpalm-<name>.service``;
``DEFAULT_RESTART_S`` for the link simulator and the lab world, which have no
unit), as ``Restart=on-failure`` would: the demo never asks a child to stop
before its end, so any exit is a failure. The shipped units never give up
(``StartLimitIntervalSec=0``: a device may come back after an hour); a demo
that restarted a broken child forever would hide the fault, so here a child
restarted ``START_LIMIT_BURST`` times within ``START_LIMIT_INTERVAL_S`` is
given up on (systemd's own default burst), which ends the demo when the child
is essential (without it nothing is demonstrated) and leaves the demo running
without it otherwise (the video).

A child can bring others down with it (``restarts_too``): a restarted lab
world listens on new ports, so the robot node and the video server, which
found it through its addresses file, are restarted after it (systemd's
``PartOf=``), once it is ready again (``after_ready`` has written its new
addresses).

``add`` starts a child and, by default, waits for its ``READY=1``, as
systemd starts a unit ordered ``After=`` another only once that one is
ready: a child that fails while the demo starts (a wrong setting) ends it at
once with its log (:class:`~deploy.units.readiness.NotReady`). Restarts are
armed only once the demo is up.

A child may have an ``ExecStopPost=`` (``StopPost``): a command run after
every end of its process, before the restart, as systemd runs the unit's.
The operator's lifts the palm (``deepxpalm palm lift``): the servos keep
their last goal when the node dies. The fault matrix's supervisor uses the
same ``StopPost``.

The fault matrix (``harness.faults.deployment``) runs the same supervisor
on a thread of its own (``start_thread``), with the shipped units' own rules
per child: ``restart_on`` (``Restart=``: which ends restart it; a process
of no unit is never restarted), no start limit (``start_limit_burst=None``,
as the shipped units), and ``hold`` while it restarts a child itself
(``systemctl restart``).

A child may have a watchdog (``deploy.units.watchdog.UnitWatchdog``, the unit's
``WatchdogSec=``): a child that said ``READY=1`` on its notify socket and then
stopped saying ``WATCHDOG=1`` (frozen, SIGSTOP, a stuck loop) is sent SIGABRT
and SIGCONT, as systemd's watchdog does; its end then runs the
``ExecStopPost=`` and the restart as any other end.
"""

from __future__ import annotations

import logging
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

from deploy.units.catalogue import DEFAULT_RESTART_S, UNITS
from deploy.units.child import START_LIMIT_BURST, START_LIMIT_INTERVAL_S, Child, ended_by
from deploy.units.process import CLEAN_ENDS, STOP_TIMEOUT_S, stop
from deploy.units.readiness import NotReady

log = logging.getLogger(__name__)


class Supervisor:
    """Watches the children; ``poll()`` restarts or gives up; ``stop_all()`` at the end."""

    def __init__(self, name: str = "demo") -> None:
        self.name = name  # what the log lines say it supervises
        self.children: dict[str, Child] = {}
        self.armed = False  # set once the demo is up; before, an exit is a startup failure
        self.events: list[str] = []  # what happened, for the summary
        self._lock = threading.RLock()  # a poll, or a child held (``hold``)
        self._held: set[str] = set()  # restarted by someone else just now: not watched
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def add(
        self, child: Child, ready: bool = True, stop_event: threading.Event | None = None
    ) -> Child:
        """Start ``child``; with ``ready``, once it said READY=1 (``NotReady`` otherwise: the
        caller stops every child, this one included)."""
        self.children[child.name] = child
        child.spawn()
        if ready:
            child.wait_ready(stop_event)
        return child

    def procs(self) -> list[tuple[str, subprocess.Popen, Path]]:
        """(name, process, log) of each child, as ``deploy.demo`` helpers take them."""
        return [(c.name, c.proc, c.log_path) for c in self.children.values() if c.proc]

    def poll(self, errors: list[str]) -> bool:
        """Restart what died, when due; False when the demo must end (see ``errors``)."""
        with self._lock:
            return self._poll(errors)

    def _poll(self, errors: list[str]) -> bool:
        now = time.monotonic()
        for child in list(self.children.values()):
            if child.gave_up or child.name in self._held:
                continue
            if child.watch is not None:
                child.watch(child)
            if child.restart_at is None:
                code = child.proc.poll() if child.proc is not None else None
                if code is None:
                    if child.watchdog is not None and child.proc is not None:
                        child.watchdog.check(child.proc.pid)
                    child.took_ready()
                    continue
                if child.stop_post is not None and not child.stop_post.done(child.started_at):
                    continue  # its ExecStopPost first (the palm lifted), then the rest
                if not self.armed:
                    errors.append(f"{child.name} stopped early with {code}; see {child.log_path}")
                    return False
                if child.restart_on is not None and not child.restart_on(code):
                    continue  # its Restart= leaves it ended
                self._died(child, code, now)
            if child.gave_up:
                if child.essential:
                    return False
                continue
            if child.restart_at is not None and now >= child.restart_at:
                self._restart(child, now)
        return True

    def _died(self, child: Child, code: int, now: float) -> None:
        child.exits.append(code)
        recent = [t for t in child.restart_times if now - t < START_LIMIT_INTERVAL_S]
        burst = child.start_limit_burst
        if burst is not None and len(recent) >= burst:
            child.gave_up = True
            self._say(
                logging.ERROR,
                f"{child.name} exited with {code} after {len(recent)} restarts in "
                f"{START_LIMIT_INTERVAL_S:.0f} s: given up on"
                + ("" if child.essential else "; the demo runs on without it")
                + f"; see {child.log_path}",
            )
            return
        child.restart_at = now + child.restart_delay_s
        self._say(
            logging.WARNING,
            f"{child.name} (pid {child.proc.pid}) exited with {code}{ended_by(child)}: "
            f"restarting in {child.restart_delay_s:g} s; see {child.log_path}",
        )

    def _restart(self, child: Child, now: float) -> None:
        child.restart_at = None
        child.restart_times.append(now)
        try:
            child.spawn()
            if child.restarts_too:
                child.wait_ready()  # its new addresses, before those who use them start
        except (OSError, NotReady) as e:  # it did not come up (the lab world): a failure
            self._say(logging.WARNING, f"{child.name} did not start again: {e}")
            stop(child.proc, 0)
            self._died(child, child.proc.returncode if child.proc else -1, time.monotonic())
            return
        self._say(logging.WARNING, f"{child.name} restarted (pid {child.proc.pid})")
        for name in child.restarts_too:
            dependent = self.children.get(name)
            if dependent is None or dependent.gave_up or dependent.restart_at is not None:
                continue
            stop(dependent.proc)
            dependent.restart_times.append(now)
            dependent.spawn()
            self._say(
                logging.WARNING,
                f"{name} restarted with {child.name} (pid {dependent.proc.pid})",
            )

    def _say(self, level: int, message: str) -> None:
        log.log(level, "%s: %s", self.name, message)
        self.events.append(f"{time.strftime('%H:%M:%S')} {message}")

    def hold(self, name: str) -> None:
        """Not watched until ``release``: restarted by the caller (``systemctl restart``)."""
        with self._lock:
            self._held.add(name)

    def release(self, name: str) -> None:
        with self._lock:
            self._held.discard(name)

    def start_thread(self, period_s: float = 0.02) -> None:
        """``poll`` every ``period_s`` on a thread until ``close``. A restarted child is forked
        from that thread, which lives as long as the supervisor (a child's PR_SET_PDEATHSIG
        follows the thread that forked it)."""
        self.armed = True

        def run() -> None:
            while not self._stop.wait(period_s):
                errors: list[str] = []
                try:
                    if not self.poll(errors):
                        for error in errors:
                            log.error("%s: %s", self.name, error)
                except Exception:  # a watch hook's bug must not end the supervision
                    log.exception("%s: poll failed", self.name)

        self._thread = threading.Thread(target=run, name=f"{self.name}-supervisor", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """The thread ended; the children are the caller's to stop (``stop_all``)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5)

    def status_line(self) -> str:
        """One line for the live view: each child's state and restarts."""
        parts = []
        for c in self.children.values():
            n = len(c.restart_times)
            parts.append(f"{c.name} {c.state}" + (f" ({n} restart{'s' * (n > 1)})" if n else ""))
        return "processes: " + "  ".join(parts)

    def summary(self) -> dict[str, Any]:
        return {
            "children": {name: c.describe() for name, c in self.children.items()},
            "events": self.events,
            "policy": (
                f"a child that exits is restarted after its unit's RestartSec "
                f"(robot {_restart_s('robot'):g} s, operator {_restart_s('operator'):g} s, "
                f"video {_restart_s('video'):g} s, "
                f"others {DEFAULT_RESTART_S:g} s), given up on after {START_LIMIT_BURST} "
                f"restarts in {START_LIMIT_INTERVAL_S:.0f} s"
            ),
        }

    def stop_all(self, errors: list[str], timeout_s: float = STOP_TIMEOUT_S) -> None:
        """Every running child stopped, as systemd stops units with no ordering between
        them: the nodes' processes together, then what outlives them (the network, the
        router, the simulated hardware: ``UnitSpec.outlives_the_nodes``) together. One
        after another, a cell's three fabric clients took 4 s. A given-up one, one that had
        to be killed, and one that ended badly are errors. Their notify sockets are closed."""
        children = list(reversed(self.children.values()))
        for outlives in (False, True):
            wave = [c for c in children if c.service.spec.outlives_the_nodes == outlives]
            threads = [
                threading.Thread(
                    target=self._stop_child, args=(c, errors, timeout_s), name=f"stop-{c.name}"
                )
                for c in wave
            ]
            for t in threads:
                t.start()
            for t in threads:
                t.join()

    def _stop_child(self, child: Child, errors: list[str], timeout_s: float) -> None:
        try:
            if child.gave_up:
                errors.append(
                    f"{child.name} was given up on after {len(child.restart_times)} "
                    f"restarts; see {child.log_path}"
                )
            elif child.proc is not None and child.restart_at is None:
                code = child.proc.poll()
                if code is not None and self.armed and child.stop_post is not None:
                    # it ended on its own a moment ago, and its ExecStopPost (the palm's
                    # lift) was still running: the lift ends, the end counts as any other,
                    # and no restart follows (Ctrl-C just after a watchdog's kill)
                    child.stop_post.run(child.started_at)
                    child.exits.append(code)
                    self._say(
                        logging.WARNING,
                        f"{child.name} (pid {child.proc.pid}) exited with {code}"
                        f"{ended_by(child)} as the demo stopped; see {child.log_path}",
                    )
                else:
                    _stop_and_report(child, errors, timeout_s)
        except Exception as e:  # one child's stop must not leave the others running
            errors.append(f"{child.name}: its stop failed: {e}")
        finally:
            child.service.close()


def _stop_and_report(child: Child, errors: list[str], timeout_s: float) -> None:
    """``systemctl stop``; a kill, or an end that was no clean stop, is reported."""
    if child.service.stop(timeout_s):
        errors.append(f"{child.name} did not stop within {timeout_s:g} s and was killed")
    code = child.proc.returncode
    if code not in CLEAN_ENDS:
        errors.append(f"{child.name} exited with {code}: {child.service.log_tail(5)}")


def _restart_s(name: str) -> float:
    """``RestartSec=`` of a catalogue unit."""
    return UNITS[name].policy.restart_sec
