"""systemd's watchdog for one unit's process, on the unit's notify socket.

A unit with ``WatchdogSec=`` hands its process ``$WATCHDOG_USEC`` beside
``$NOTIFY_SOCKET``; once the process says ``READY=1``, a silence of
``WatchdogSec`` without ``WATCHDOG=1`` makes systemd send the watchdog signal
(SIGABRT) followed by SIGCONT (so a stopped process runs and dies), then
SIGKILL after ``TimeoutAbortSec=``. ``UnitWatchdog`` does the same for a
process that ``deepxpalm demo`` or the fault matrix starts under a shipped
unit's rules (``deploy.units.supervisor``), so a frozen node is ended as on
the deployed machine, and its unit's ``ExecStopPost=`` then runs. It reads
the pings from the child's :class:`~deploy.units.readiness.NotifySocket`,
the one its readiness is read from.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
import time

from deploy.units.readiness import NotifySocket

log = logging.getLogger(__name__)


class UnitWatchdog:
    """``check(pid)`` ends a process of the unit that said READY=1 and then stopped pinging."""

    def __init__(self, notify: NotifySocket, watchdog_sec: float, timeout_abort_sec: float) -> None:
        self.notify = notify
        self.watchdog_sec = watchdog_sec
        self.timeout_abort_sec = timeout_abort_sec
        self._lock = threading.Lock()
        self._abort_sent_at: float | None = None
        self._aborted_pid: int | None = None
        #: (monotonic s, pid) of each process the watchdog ended
        self.fired: list[tuple[float, int]] = []

    def environ(self) -> dict[str, str]:
        """What systemd adds to the unit's environment for its watchdog."""
        return {"WATCHDOG_USEC": str(round(self.watchdog_sec * 1e6))}

    @property
    def pings(self) -> int:
        return self.notify.pings

    @property
    def armed(self) -> bool:
        """The unit's current process said READY=1: from now on a silence ends it (before that,
        systemd's TimeoutStartSec= would)."""
        return self.notify.ready is not None

    def check(self, pid: int) -> None:
        """SIGABRT + SIGCONT to ``pid`` after a silence of WatchdogSec; SIGKILL after
        TimeoutAbortSec more, as systemd's watchdog does."""
        now = time.monotonic()
        last_ping = self.notify.last_ping(pid)
        with self._lock:
            if self._aborted_pid == pid:
                if now - self._abort_sent_at > self.timeout_abort_sec:
                    self._aborted_pid = None
                    with contextlib.suppress(ProcessLookupError):
                        os.kill(pid, signal.SIGKILL)  # TimeoutAbortSec= passed
                return
            if last_ping is None or now - last_ping <= self.watchdog_sec:
                return
            self._aborted_pid, self._abort_sent_at = pid, now
            self.fired.append((now, pid))
        log.warning("watchdog: pid %d silent for %.1f s: SIGABRT", pid, now - last_ping)
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGABRT)
            os.kill(pid, signal.SIGCONT)
