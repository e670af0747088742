"""systemd's notify socket and watchdog for one unit's process, as the harness plays systemd.

A unit with ``WatchdogSec=`` hands its process ``$NOTIFY_SOCKET`` and
``$WATCHDOG_USEC``; once the process says ``READY=1``, a silence of
``WatchdogSec`` without ``WATCHDOG=1`` makes systemd send the watchdog signal
(SIGABRT) followed by SIGCONT (so a stopped process runs and dies), then
SIGKILL after ``TimeoutAbortSec=``. ``UnitWatchdog`` does the same for a
process that ``deepxpalm demo`` or the fault matrix starts under a shipped
unit's rules (``deploy/supervisor.py``), so a frozen node is ended as on the
deployed machine, and its unit's ``ExecStopPost=`` then runs.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import socket
import threading
import time
from pathlib import Path

log = logging.getLogger(__name__)


class UnitWatchdog:
    """The notify socket of one unit; ``check(pid)`` ends a process that stopped pinging."""

    def __init__(self, path: Path, watchdog_sec: float, timeout_abort_sec: float) -> None:
        self.path = path
        self.watchdog_sec = watchdog_sec
        self.timeout_abort_sec = timeout_abort_sec
        path.unlink(missing_ok=True)
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._sock.bind(str(path))
        self._sock.settimeout(0.1)
        self._lock = threading.Lock()
        self._ready_at: float | None = None
        self._last_ping: float | None = None
        self._abort_sent_at: float | None = None
        self._aborted_pid: int | None = None
        #: (monotonic s, pid) of each process the watchdog ended
        self.fired: list[tuple[float, int]] = []
        self.pings = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._listen, name="notify-socket", daemon=True)
        self._thread.start()

    def environ(self) -> dict[str, str]:
        """What systemd puts in the unit's environment."""
        return {
            "NOTIFY_SOCKET": str(self.path),
            "WATCHDOG_USEC": str(round(self.watchdog_sec * 1e6)),
        }

    def started(self) -> None:
        """A new process of the unit: unarmed until it says READY=1."""
        with self._lock:
            self._ready_at = self._last_ping = self._abort_sent_at = None
            self._aborted_pid = None

    @property
    def armed(self) -> bool:
        """The unit's current process said READY=1: from now on a silence ends it (before that,
        systemd's TimeoutStartSec= would)."""
        with self._lock:
            return self._ready_at is not None

    def _listen(self) -> None:
        while not self._stop.is_set():
            try:
                data = self._sock.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                return
            now = time.monotonic()
            lines = data.decode(errors="replace").splitlines()
            with self._lock:
                if "READY=1" in lines:
                    self._ready_at = self._last_ping = now
                if "WATCHDOG=1" in lines:
                    self._last_ping = now
                    self.pings += 1

    def check(self, pid: int) -> None:
        """SIGABRT + SIGCONT to ``pid`` after a silence of WatchdogSec; SIGKILL after
        TimeoutAbortSec more, as systemd's watchdog does."""
        now = time.monotonic()
        with self._lock:
            if self._aborted_pid == pid:
                if now - self._abort_sent_at > self.timeout_abort_sec:
                    self._aborted_pid = None
                    with contextlib.suppress(ProcessLookupError):
                        os.kill(pid, signal.SIGKILL)
                return
            if self._last_ping is None or now - self._last_ping <= self.watchdog_sec:
                return
            self._aborted_pid, self._abort_sent_at = pid, now
            self.fired.append((now, pid))
        log.warning("watchdog: pid %d silent for %.1f s: SIGABRT", pid, now - self._last_ping)
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGABRT)
            os.kill(pid, signal.SIGCONT)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        self._sock.close()
        self.path.unlink(missing_ok=True)
