"""One child of the supervisor: its service, its restarts, its ``ExecStopPost=``.

A :class:`Child` is a :class:`~deploy.units.service.Service` and what the
supervisor (``deploy.units.supervisor``) keeps of it: when it restarts, what
it did, what its unit runs after each of its ends (:class:`StopPost`, the
operator's palm lift), and what the caller does with each process's
``READY=1`` (``after_ready``).
"""

from __future__ import annotations

import logging
import subprocess
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from deploy.units.catalogue import UnitSpec
from deploy.units.process import spawn, stop
from deploy.units.readiness import Ready
from deploy.units.service import Service
from deploy.units.watchdog import UnitWatchdog

log = logging.getLogger(__name__)

START_LIMIT_BURST = 5
START_LIMIT_INTERVAL_S = 60.0


def stop_post_args(stop_post: tuple[str, ...], config: Path) -> list[str]:
    """A unit's ``ExecStopPost=`` arguments with ``config`` for the installed config it names
    (``/etc/deepxpalm/...``): the same command, on this run's config."""
    return [str(config) if a.startswith("/etc/deepxpalm/") else a for a in stop_post]


class StopPost:
    """A unit's ``ExecStopPost=``: ``start()`` spawns the command once per end of the process;
    ``done()`` polls it (never blocks the supervisor's loop) and records each run."""

    def __init__(self, name: str, start: Callable[[], subprocess.Popen]) -> None:
        self.name = name
        self.start = start
        #: (monotonic start, end, exit code) of each run
        self.runs: list[tuple[float, float, int]] = []
        self._running: tuple[float, subprocess.Popen] | None = None
        self._ran_for: float | None = None  # the process start (monotonic) its last run followed

    @classmethod
    def of(cls, spec: UnitSpec, config: Path, log_path: Path) -> StopPost | None:
        """``spec``'s unit's ``ExecStopPost=`` on this run's ``config``, at the unit's
        ``Nice=`` as systemd runs every command of the unit; None when it has none."""
        if not spec.stop_post:
            return None
        argv = ["-v", *stop_post_args(spec.stop_post, config)]
        return cls(spec.name, lambda: spawn(spec.unit, argv, log_path))

    def done(self, started_at: float) -> bool:
        """Whether the run after the end of the process started at ``started_at`` is over
        (it is started on the first call for that process)."""
        if self._ran_for == started_at:
            return True
        if self._running is None:
            self._running = (time.monotonic(), self.start())
            return False
        t0, popen = self._running
        code = popen.poll()
        if code is None:
            return False
        self._record(t0, code)
        self._ran_for = started_at
        return True

    def run(self, started_at: float, timeout_s: float = 60.0) -> int:
        """To its end (a clean restart: systemd runs it between stop and start)."""
        while not self.done(started_at):
            if self._running is not None and time.monotonic() - self._running[0] > timeout_s:
                stop(self._running[1])
            time.sleep(0.01)
        return self.runs[-1][2]

    def _record(self, t0: float, code: int) -> None:
        self._running = None
        self.runs.append((t0, time.monotonic(), code))
        level = logging.INFO if code == 0 else logging.ERROR
        log.log(
            level,
            "%s: ExecStopPost ended with %s in %.2f s",
            self.name,
            code,
            time.monotonic() - t0,
        )


@dataclass
class Child:
    """One process of the demo: its service, and how the supervisor keeps it running."""

    service: Service
    #: ``RestartSec=``; None: its unit's
    restart_delay_s: float | None = None
    essential: bool = True  # given up on: the demo ends
    restarts_too: tuple[str, ...] = ()  # restarted after this one (they depend on it)
    stop_post: StopPost | None = None  # run after every end, before the restart
    #: what the demo does with each process's READY=1 (a restarted world's new addresses
    #: written for the processes restarted with it), once per process
    after_ready: Callable[[Ready], None] | None = None
    ready_pid: int | None = None  # the process whose READY=1 after_ready took
    pids: list[int] = field(default_factory=list)
    exits: list[int] = field(default_factory=list)  # return codes of the unexpected exits
    restart_times: list[float] = field(default_factory=list)  # monotonic
    restart_at: float | None = None  # when a restart is due
    gave_up: bool = False
    started_at: float = 0.0  # monotonic, the running process's start
    #: ``Restart=``: whether an end with this code restarts it; None: any end (the demo never
    #: stops a child before its end, so any end is a failure)
    restart_on: Callable[[int], bool] | None = None
    #: restarts within START_LIMIT_INTERVAL_S before it is given up on; None: never (as the
    #: shipped units, ``StartLimitIntervalSec=0``)
    start_limit_burst: int | None = START_LIMIT_BURST
    #: called with the child on every poll (what it reports: the fault matrix reads the
    #: operator's status file)
    watch: Callable[[Child], None] | None = None

    def __post_init__(self) -> None:
        if self.restart_delay_s is None:
            self.restart_delay_s = self.service.spec.policy.restart_sec

    @property
    def name(self) -> str:
        return self.service.name

    @property
    def proc(self) -> subprocess.Popen | None:
        return self.service.popen

    @property
    def log_path(self) -> Path:
        return self.service.log

    @property
    def watchdog(self) -> UnitWatchdog | None:
        return self.service.watchdog

    @property
    def incarnation(self) -> int:
        """Which process of the child runs: 0 the first, 1 after one restart ..."""
        return self.service.starts - 1

    def spawn(self) -> None:
        self.started_at = time.monotonic()
        self.pids.append(self.service.start().pid)

    def wait_ready(self, stop_event: threading.Event | None = None) -> Ready:
        """Its READY=1 (NotReady when it ends first or takes too long), then ``after_ready``."""
        ready = self.service.wait_ready(stop_event=stop_event)
        self._took(ready)
        return ready

    def took_ready(self) -> None:
        """``after_ready`` once the running process said READY=1 (never waits)."""
        ready = self.service.ready
        if ready is not None:
            self._took(ready)

    def _took(self, ready: Ready) -> None:
        pid = self.proc.pid if self.proc is not None else None
        if self.ready_pid != pid:
            self.ready_pid = pid
            if self.after_ready is not None:
                self.after_ready(ready)

    @property
    def state(self) -> str:
        if self.gave_up:
            return "gave up"
        if self.restart_at is not None:
            return "restarting"
        return "running"

    def describe(self) -> dict[str, Any]:
        return {
            "state": self.state,
            "pid": self.proc.pid if self.proc is not None and self.state == "running" else None,
            "restarts": len(self.restart_times),
            "exit_codes": self.exits,
            "pids": self.pids,
            "log": str(self.log_path),
            **(
                {}
                if self.stop_post is None
                else {  # each ExecStopPost run: how long it took, how it ended
                    "stop_post": [
                        {"took_s": round(end - start, 3), "exit_code": code}
                        for start, end, code in self.stop_post.runs
                    ]
                }
            ),
        }


def ended_by(child: Child) -> str:
    """What the log says of a process its unit's watchdog ended."""
    watchdog, proc = child.watchdog, child.proc
    if watchdog is None or proc is None:
        return ""
    return " (ended by its watchdog)" if any(p == proc.pid for _, p in watchdog.fired) else ""
