"""Which subscriber connections ended on a relay path, counted and logged.

libzmq ends a connection itself when a peer sends a frame over the socket's
``MAXMSGSIZE`` (the relay's 64 KiB on its subscriber side): the relay never
reads a byte of that frame, and nothing but a ``DISCONNECTED`` monitor event
with the connection's socket fd tells it. The same event comes when a
subscriber closes. So each ending is counted (``subscriber_connections_ended``)
and logged with what is known of the connection: its address (read when it
was accepted) and, if it sent anything before, its key. A connection that
ends while its peer still holds it open is the relay's doing.
"""

from __future__ import annotations

import contextlib
import logging
import os
import socket
from collections import Counter

import zmq
from zmq.utils.monitor import parse_monitor_message

from common.logs import BurstLog

log = logging.getLogger(__name__)


def _peer_address(fd: int) -> str:
    """``host:port`` of the peer on ``fd`` (a libzmq-owned socket, read through a copy)."""
    try:
        dup = os.dup(fd)
    except OSError:
        return "an unknown address"
    try:
        copy = socket.socket(fileno=dup)
    except OSError:
        os.close(dup)
        return "an unknown address"
    try:
        host, port = copy.getpeername()[:2]
        return f"{host}:{port}"
    except (OSError, ValueError):
        return "an unknown address"
    finally:
        copy.close()  # the copy only: libzmq's socket stays open


class ConnectionLog:
    """The monitor of one subscriber-side socket; call ``handle`` when ``monitor`` is readable."""

    def __init__(self, sock: zmq.Socket, what: str, counters: Counter[str]) -> None:
        self.monitor = sock.get_monitor_socket(zmq.EVENT_ACCEPTED | zmq.EVENT_DISCONNECTED)
        self._sock = sock
        self._counters = counters
        self._address: dict[int, str] = {}
        self._sender: dict[int, str] = {}
        # at info: a subscriber leaving is ordinary; a burst of endings is summarised
        self._ended = BurstLog(
            log,
            f"subscriber connection ended at the relay ({what})",
            interval_s=1.0,
            level=logging.INFO,
        )

    def heard(self, fd: int, who: str) -> None:
        """A frame from the connection on ``fd`` (``who``: its key and connection number)."""
        if fd >= 0:
            self._sender[fd] = who

    def handle(self) -> None:
        while self.monitor.get(zmq.EVENTS) & zmq.POLLIN:
            event = parse_monitor_message(self.monitor.recv_multipart(zmq.NOBLOCK))
            fd = int(event["value"])
            if event["event"] == zmq.EVENT_ACCEPTED:
                self._address[fd] = _peer_address(fd)
                self._sender.pop(fd, None)  # a new connection on a reused fd
            elif event["event"] == zmq.EVENT_DISCONNECTED:
                self._counters["subscriber_connections_ended"] += 1
                address = self._address.pop(fd, "an unknown address")
                who = self._sender.pop(fd, "a key that had sent nothing")
                self._ended(
                    f"{who} from {address}: it closed, or sent a frame over 64 KiB, which ends "
                    "the connection before the relay reads it"
                )

    def close(self) -> None:
        with contextlib.suppress(zmq.ZMQError):
            self._sock.disable_monitor()
        self.monitor.close(0)
