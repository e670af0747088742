"""One unit's process as the demo and the harness run it, the way systemd runs a unit.

A :class:`Service` is one catalogue entry (``deploy.units.catalogue``) with the
run's own arguments and log: :meth:`Service.start` spawns it
(``deploy.units.process.spawn``: its unit's niceness, dying with its parent)
with a notify socket of its own, and with its unit's watchdog environment when
the unit has ``WatchdogSec=``; :meth:`Service.wait_ready` returns what its
``READY=1`` said (the endpoints it bound); :meth:`Service.stop` is
``systemctl stop``. A service started again (a restart) keeps its notify
socket and its log, as a unit keeps its socket and its journal.
"""

from __future__ import annotations

import os
import signal
import subprocess
import threading
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import IO, Any

from deploy.units.catalogue import UnitSpec, unit
from deploy.units.process import STOP_TIMEOUT_S, spawn, stop
from deploy.units.readiness import NotifySocket, Ready, log_tail
from deploy.units.watchdog import UnitWatchdog


class Service:
    """A catalogue entry's process, started, waited for, stopped and started again.

    ``log``: where its output goes (None: ours). ``argv``: the whole ``deepxpalm`` argument
    list, or a function of the start's number (0 first, then 1, 2 ... after restarts: a
    restarted node records beside the crashed one's file). ``name``: what logs and the
    notify socket call it (default: the unit's).
    ``watchdog``: run under the unit's ``WatchdogSec=`` (when it has one). ``env``: its
    whole environment (None: ours); the notify socket's variables are added to it.
    Other keywords go to :func:`deploy.units.process.spawn` (``stdout=``, ``text=``).
    """

    def __init__(
        self,
        spec: UnitSpec | str,
        argv: list[str] | Callable[[int], list[str]],
        log: Path | None,
        *,
        name: str | None = None,
        env: Mapping[str, str] | None = None,
        stdin: IO[Any] | int | None = subprocess.DEVNULL,
        watchdog: bool = True,
        **spawn_kw: Any,
    ) -> None:
        self.spec = unit(spec) if isinstance(spec, str) else spec
        self.name = name or self.spec.name
        self.argv = argv if callable(argv) else (lambda _n, fixed=list(argv): fixed)
        self.log = log
        self.env = env
        self.stdin = stdin
        self.spawn_kw = spawn_kw
        self.notify = NotifySocket(self.name)
        rule = self.spec.policy
        self.watchdog = (
            UnitWatchdog(self.notify, rule.watchdog_sec, rule.timeout_abort_sec)
            if watchdog and rule.watchdog_sec > 0
            else None
        )
        self.popen: subprocess.Popen | None = None
        self.starts = 0  # how many processes it has been

    # ------------------------------------------------------------ starting
    def start(self) -> subprocess.Popen:
        """Its next process (the first, or a restart's), its notify socket listening to it."""
        env = {**(os.environ if self.env is None else self.env), **self.notify.environ()}
        if self.watchdog is not None:
            env.update(self.watchdog.environ())
        self.popen = spawn(
            self.spec.unit,
            self.argv(self.starts),
            self.log,
            env,
            self.stdin,
            **self.spawn_kw,
        )
        self.starts += 1
        self.notify.started(self.popen.pid)
        return self.popen

    def wait_ready(
        self, timeout_s: float | None = None, stop_event: threading.Event | None = None
    ) -> Ready:
        """What its running process said with READY=1, once it says it (see
        :meth:`NotifySocket.wait_ready`); its unit's start timeout by default."""
        assert self.popen is not None, f"{self.name} was never started"
        timeout = self.spec.start_timeout_s if timeout_s is None else timeout_s
        return self.notify.wait_ready(self.popen, timeout, self.log, stop_event)

    def up(self, timeout_s: float | None = None) -> Ready:
        """Started and ready (a process that is not ready in time is stopped)."""
        self.start()
        try:
            return self.wait_ready(timeout_s)
        except BaseException:
            self.stop(0)
            raise

    @property
    def ready(self) -> Ready | None:
        """What the running process said with READY=1; None before it did."""
        return self.notify.ready

    # ------------------------------------------------------------ running
    @property
    def pid(self) -> int:
        assert self.popen is not None
        return self.popen.pid

    def alive(self) -> bool:
        return self.popen is not None and self.popen.poll() is None

    def log_text(self) -> str:
        if self.log is None or not self.log.exists():
            return ""
        return self.log.read_text(errors="replace")

    def log_tail(self, lines: int = 8) -> str:
        return log_tail(self.log, lines)

    # ------------------------------------------------------------ stopping
    def stop(
        self, timeout_s: float = STOP_TIMEOUT_S, sig: int = signal.SIGTERM, group: bool = False
    ) -> bool:
        """``systemctl stop``: ``sig``, a wait of ``timeout_s``, SIGKILL; True if killed.
        ``group``: its whole process group (a demo and its children)."""
        return stop(self.popen, timeout_s, sig, group=group)

    def close(self) -> None:
        """Its notify socket closed (the process is the caller's to have stopped)."""
        self.notify.close()
