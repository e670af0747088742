"""Readiness as systemd reads it: a notify socket per child, and what its ``READY=1`` says.

A unit with ``Type=notify`` is started when its process says ``READY=1`` on
the datagram socket named in its ``$NOTIFY_SOCKET``, not when a line appears
in its log or a file on disk. :class:`NotifySocket` is that socket for one
child of the demo or the harness: an abstract AF_UNIX socket (no path to
clean up or to outgrow ``sun_path``), listened to on a thread of its own,
that takes a datagram only from the process it was told about
(``NotifyAccess=main``: the kernel's credentials say who sent it, so a
grandchild that inherited the variable cannot speak for its parent).

Every process of the product says ``READY=1`` through
``common.process.sd_notify.Notifier`` once it serves, with what it bound:
``STATUS=`` for people and ``X_DEEPXPALM_ENDPOINTS=`` (JSON) for its
parent, so a process binds port 0 and reports the port instead of being
handed one. :meth:`NotifySocket.wait_ready` returns those fields
(:class:`Ready`), or raises :class:`NotReady` with the end of the child's log.
The watchdog (``deploy.units.watchdog``) reads ``WATCHDOG=1`` from the same
socket.
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import socket
import struct
import subprocess
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from common.process.sd_notify import ENDPOINTS_FIELD, FIELD_PREFIX

_CREDS = struct.Struct("3i")  # struct ucred: pid, uid, gid


class NotReady(RuntimeError):
    """A child ended, or said nothing, before ``READY=1``; the message holds its log's tail."""


@dataclass(frozen=True)
class Ready:
    """What a process said with its ``READY=1``: ``KEY=VALUE`` fields, and when (monotonic s)."""

    at: float
    fields: dict[str, str]

    @property
    def status(self) -> str:
        return self.fields.get("STATUS", "")

    @property
    def endpoints(self) -> dict[str, Any]:
        """``X_DEEPXPALM_ENDPOINTS``: what it bound or serves ({} when it said nothing)."""
        text = self.fields.get(ENDPOINTS_FIELD)
        return {} if not text else json.loads(text)

    def field(self, name: str) -> str | None:
        """A ``X_DEEPXPALM_<NAME>`` field (``schedule_start_ns``), or None."""
        return self.fields.get(FIELD_PREFIX + name.upper())


@dataclass
class _Process:
    """What one process has said so far."""

    ready: Ready | None = None
    last_ping: float | None = None
    pings: int = 0
    status: str = ""
    readies: list[Ready] = field(default_factory=list)
    #: the newest value of every field it said, READY=1 or not
    said: dict[str, str] = field(default_factory=dict)


def log_tail(log: Path | None, lines: int = 8) -> str:
    """The last ``lines`` of a log, joined for one message ("" without one)."""
    if log is None or not log.exists():
        return ""
    with contextlib.suppress(OSError):
        return " | ".join(log.read_text(errors="replace").strip().splitlines()[-lines:])
    return ""


class NotifySocket:
    """One child's ``$NOTIFY_SOCKET``, across the processes it is started as."""

    def __init__(self, name: str) -> None:
        self.name = name
        #: as systemd writes an abstract address: '@' for the leading NUL
        self.address = f"@deepxpalm/{os.getpid()}/{name}/{secrets.token_hex(6)}"
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_PASSCRED, 1)
        self._sock.bind("\0" + self.address[1:])
        self._sock.settimeout(0.1)
        self._changed = threading.Condition()
        self._by_pid: dict[int, _Process] = {}
        self.pid: int | None = None  # the process listened to (NotifyAccess=main)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._listen, name=f"notify-{name}", daemon=True)
        self._thread.start()

    def environ(self) -> dict[str, str]:
        """What systemd puts in the unit's environment for its notify socket."""
        return {"NOTIFY_SOCKET": self.address}

    def started(self, pid: int) -> None:
        """A new process of the unit: listened to from now on, not ready until it says so."""
        with self._changed:
            self.pid = pid
            self._by_pid.setdefault(pid, _Process())
            self._changed.notify_all()

    def _listen(self) -> None:
        cmsg_size = socket.CMSG_SPACE(_CREDS.size)
        while not self._stop.is_set():
            try:
                data, ancdata, _, _ = self._sock.recvmsg(65536, cmsg_size)
            except TimeoutError:
                continue
            except OSError:
                return
            pid = _sender(ancdata)
            if pid is None:
                continue
            now = time.monotonic()
            fields: dict[str, str] = {}
            for line in data.decode(errors="replace").splitlines():
                key, sep, value = line.partition("=")
                if sep:
                    fields[key] = value
            with self._changed:
                said = self._by_pid.setdefault(pid, _Process())
                said.said.update(fields)
                if fields.get("READY") == "1":
                    said.ready = Ready(now, fields)
                    said.readies.append(said.ready)
                    said.last_ping = now
                if fields.get("WATCHDOG") == "1":
                    said.last_ping = now
                    said.pings += 1
                if "STATUS" in fields:
                    said.status = fields["STATUS"]
                self._changed.notify_all()

    def _current(self) -> _Process | None:
        return None if self.pid is None else self._by_pid.get(self.pid)

    @property
    def ready(self) -> Ready | None:
        """What the current process said with its ``READY=1``; None before it did."""
        with self._changed:
            said = self._current()
            return None if said is None else said.ready

    @property
    def status(self) -> str:
        """The current process's latest ``STATUS=``."""
        with self._changed:
            said = self._current()
            return "" if said is None else said.status

    def field(self, name: str) -> str | None:
        """The newest ``X_DEEPXPALM_<NAME>`` the current process said (None: never)."""
        with self._changed:
            said = self._current()
            return None if said is None else said.said.get(FIELD_PREFIX + name.upper())

    def wait_field(self, name: str, other_than: str | None, timeout_s: float) -> str | None:
        """Until the current process says ``X_DEEPXPALM_<NAME>`` with a value other than
        ``other_than``: that value (None after ``timeout_s``)."""
        deadline = time.monotonic() + timeout_s
        with self._changed:
            while (value := self.field(name)) in (None, other_than):
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._changed.wait(left)
            return value

    def last_ping(self, pid: int) -> float | None:
        """When ``pid`` last said ``READY=1`` or ``WATCHDOG=1`` (monotonic s)."""
        with self._changed:
            said = self._by_pid.get(pid)
            return None if said is None else said.last_ping

    @property
    def pings(self) -> int:
        """``WATCHDOG=1`` datagrams of every process of the unit."""
        with self._changed:
            return sum(p.pings for p in self._by_pid.values())

    def readies(self) -> list[Ready]:
        """Every ``READY=1`` of every process of the unit, in order (each start's)."""
        with self._changed:
            return sorted((r for p in self._by_pid.values() for r in p.readies), key=lambda r: r.at)

    def wait_ready(
        self,
        popen: subprocess.Popen,
        timeout_s: float,
        log: Path | None = None,
        stop: threading.Event | None = None,
    ) -> Ready:
        """Until ``popen`` says ``READY=1``: what it said. :class:`NotReady` (its log's tail
        in the message) when it ends first, or after ``timeout_s`` (systemd's
        ``TimeoutStartSec=``: the caller then stops it), or once ``stop`` is set."""
        deadline = time.monotonic() + timeout_s
        with self._changed:
            while True:
                said = self._by_pid.get(popen.pid)
                if said is not None and said.ready is not None:
                    return said.ready
                if popen.poll() is not None:
                    why = f"ended with {popen.returncode} before it was ready"
                    break
                left = deadline - time.monotonic()
                if left <= 0:
                    why = f"not ready after {timeout_s:g} s"
                    break
                if stop is not None and stop.is_set():
                    why = "not ready when asked to stop"
                    break
                self._changed.wait(min(left, 0.05))
        tail = log_tail(log)
        raise NotReady(f"{self.name} (pid {popen.pid}) {why}" + (f": {tail}" if tail else ""))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        self._sock.close()


def _sender(ancdata: list[tuple[int, int, bytes]]) -> int | None:
    """The sending process of a datagram, from its SCM_CREDENTIALS."""
    for level, kind, data in ancdata:
        if level == socket.SOL_SOCKET and kind == socket.SCM_CREDENTIALS:
            return _CREDS.unpack(data[: _CREDS.size])[0]
    return None
