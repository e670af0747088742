"""systemd's readiness and watchdog protocol, without libsystemd or any package.

A unit with ``Type=notify`` counts its service as started only when the
process says ``READY=1``; with ``WatchdogSec=`` it kills and restarts a
service that stops saying ``WATCHDOG=1``. Both are one datagram each to the
AF_UNIX socket systemd names in ``$NOTIFY_SOCKET`` (a leading ``@`` means
the abstract namespace), so a few lines of ``socket`` do it; pulling in
python-systemd for this would add a C dependency to both machines.

The watchdog must prove the node's loop is alive, not merely that the
process exists: a thread that pinged on a timer would keep a wedged node
running forever. :func:`watch_node` therefore pings only while the node's
publisher keeps sending (both nodes send a heartbeat at 20 Hz from inside
their loops), so a loop stuck in a driver call stops the pings and systemd
restarts the service. Outside systemd (no ``$NOTIFY_SOCKET``) everything
here does nothing.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import threading
from collections.abc import Callable, Mapping
from typing import Any

log = logging.getLogger(__name__)

#: systemd keeps fields it does not know; ours start with this
FIELD_PREFIX = "X_DEEPXPALM_"
#: the field of ``READY=1`` that says what the process bound or serves, as JSON
#: (``{"telemetry": "tcp://127.0.0.1:40123"}``): whoever started it reads its ports there
ENDPOINTS_FIELD = FIELD_PREFIX + "ENDPOINTS"


def _address(path: str) -> str | bytes:
    # Linux abstract sockets start with a NUL byte; systemd writes it as '@'.
    return "\0" + path[1:] if path.startswith("@") else path


class Notifier:
    """Sends state changes to systemd; a no-op when not started by a ``Type=notify`` unit."""

    def __init__(self, environ: Mapping[str, str] | None = None) -> None:
        env = os.environ if environ is None else environ
        self.socket_path: str | None = env.get("NOTIFY_SOCKET") or None
        if self.socket_path is not None and not self.socket_path.startswith(("/", "@")):
            # vsock: and other transports newer systemd offers to VMs: not needed on a node PC.
            log.warning("NOTIFY_SOCKET %r is not a unix socket; not notifying", self.socket_path)
            self.socket_path = None
        self.watchdog_interval_s: float | None = None
        usec = env.get("WATCHDOG_USEC")
        pid = env.get("WATCHDOG_PID")
        # WATCHDOG_PID names the process the watchdog is for; a child must not ping for it.
        if usec and (not pid or pid == str(os.getpid())):
            try:
                self.watchdog_interval_s = int(usec) / 1e6 or None
            except ValueError:
                log.warning("WATCHDOG_USEC %r is not an integer; watchdog off", usec)
        self._sock: socket.socket | None = None
        self._failed = False

    @property
    def enabled(self) -> bool:
        return self.socket_path is not None

    def send(self, *assignments: str) -> bool:
        """Send ``KEY=VALUE`` lines in one datagram; False when not sent (never raises)."""
        if self.socket_path is None:
            return False
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._sock.sendto("\n".join(assignments).encode(), _address(self.socket_path))
        except OSError as e:
            if not self._failed:  # once: a broken socket would otherwise log 20 times a second
                log.warning("cannot notify systemd at %s: %s", self.socket_path, e)
                self._failed = True
            return False
        return True

    def ready(
        self,
        status: str | None = None,
        endpoints: Mapping[str, Any] | None = None,
        **fields: Any,
    ) -> bool:
        """``READY=1``, with ``STATUS=status``, what the process bound (``endpoints``, as
        JSON in ``X_DEEPXPALM_ENDPOINTS``) and any ``X_DEEPXPALM_<NAME>=value`` fields."""
        extra = [f"STATUS={status}"] if status else []
        if endpoints is not None:
            extra.append(f"{ENDPOINTS_FIELD}={json.dumps(endpoints, separators=(',', ':'))}")
        extra += [f"{FIELD_PREFIX}{name.upper()}={value}" for name, value in fields.items()]
        return self.send("READY=1", *extra)

    def watchdog(self) -> bool:
        return self.send("WATCHDOG=1")

    def status(self, text: str) -> bool:
        return self.send(f"STATUS={text}")

    def stopping(self) -> bool:
        return self.send("STOPPING=1")

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None


class NodeWatch:
    """Tells systemd a node is ready once its loop publishes, and alive while it keeps doing so.

    Watches ``node.pub.sent`` (the node's publisher counter), or
    ``node.loop_turns`` where the node counts its loop's turns (the operator:
    a signed observer sends only 2 heartbeats a second), from a daemon
    thread: the first message sent (turn) means the devices are connected,
    the sockets are up and the loop runs (READY=1); each later increase
    within a quarter of the watchdog interval earns one WATCHDOG=1. ``node``
    is any object with ``pub`` (None until the sockets are open) or
    ``loop_turns``, and optionally ``link_state`` for the status line.
    ``endpoints()``, asked once at READY=1, says what the node bound or serves
    (its sockets' ports, its dashboard) for whoever started it.
    """

    #: how often the node is looked at before it is ready: its parent waits for READY=1
    READY_POLL_S = 0.02

    def __init__(
        self,
        node: Any,
        stop: threading.Event,
        notifier: Notifier,
        endpoints: Callable[[], Mapping[str, Any]] | None = None,
    ) -> None:
        self.node = node
        self.stop_event = stop
        self.notifier = notifier
        self.endpoints = endpoints
        self._done = threading.Event()
        interval = notifier.watchdog_interval_s
        self.poll_s = min(0.5, interval / 4) if interval else 0.5
        self.ready_sent = False
        self.pings = 0
        self._thread: threading.Thread | None = None

    def start(self) -> NodeWatch:
        if self.notifier.enabled:
            self._thread = threading.Thread(target=self._run, name="sd-notify", daemon=True)
            self._thread.start()
        return self

    def _sent(self) -> int | None:
        turns = getattr(self.node, "loop_turns", None)  # a node whose loop counts its turns
        if turns is not None:
            return int(turns) or None
        pub = getattr(self.node, "pub", None)
        return None if pub is None else int(getattr(pub, "sent", 0))

    def _run(self) -> None:
        last = 0
        ticks = 0
        while not self.stop_event.is_set() and not self._done.is_set():
            sent = self._sent()
            if sent is not None and sent > last:
                if not self.ready_sent:
                    bound = None if self.endpoints is None else self.endpoints()
                    self.ready_sent = self.notifier.ready(self._status_line(sent), bound)
                elif self.notifier.watchdog_interval_s:
                    self.notifier.watchdog()
                    self.pings += 1
                last = sent
                ticks += 1
                if ticks % 20 == 0:
                    self.notifier.status(self._status_line(sent))
            self._done.wait(self.poll_s if self.ready_sent else self.READY_POLL_S)
        self.notifier.stopping()

    def _status_line(self, sent: int) -> str:
        state = getattr(self.node, "link_state", "?")
        return f"link {state}, {sent} messages sent"

    def stop(self) -> None:
        """Say STOPPING=1 and end the thread (idempotent)."""
        self._done.set()
        if self._thread is not None:
            self._thread.join(timeout=2)
            self._thread = None
        self.notifier.close()


def watch_node(
    node: Any,
    stop: threading.Event,
    notifier: Notifier | None = None,
    endpoints: Callable[[], Mapping[str, Any]] | None = None,
) -> NodeWatch:
    """Start watching ``node`` for systemd (does nothing outside a ``Type=notify`` unit);
    ``endpoints()`` is what its READY=1 says it bound."""
    return NodeWatch(node, stop, notifier or Notifier(), endpoints).start()
