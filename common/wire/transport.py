"""ZeroMQ sockets for the link between the nodes.

Freshness over completeness: a subscriber drains everything queued and the
caller keeps the newest message of each kind, so a backlog never turns into
lag. Every socket has LINGER 0 (closing never blocks), a maximum message size
(oversized frames are dropped by ZeroMQ before they are read) and bounded
queues. Decoding errors are counted by class and logged once per burst.

A connecting socket may watch its connection (``reconnect=True``, with
``common.wire.connection_watch``): libzmq never reconnects after a protocol
error (an oversized or malformed frame from the peer, a handshake in a
language it does not speak), so such a socket is closed and opened again
by the next call that touches it, within a fraction of a second, and says
so in ``link_health``.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from typing import Any

import zmq

from common.clocks.clock import now_ns
from common.errors import LinkError
from common.logs import BurstLog
from common.wire.capture_link import (
    CaptureInbox,
    CaptureLink,
    CapturePublisher,
    Link,
    Receiver,
    Sender,
)
from common.wire.codec import (
    MAX_MESSAGE_BYTES,
    DecodeError,
    MultipartMessageError,
    WrongRobotError,
    decode_named,
    encode,
)
from common.wire.connection_watch import RECONNECT_GRACE_S, RECONNECT_MAX_S, ConnectionWatch
from common.wire.loopback_ports import KNOWN_PORTS_FROM, free_loopback_ports
from common.wire.messages import Message

#: ``Link``, the capture link and the loopback ports are re-exported where their users find them
__all__ = [
    "KNOWN_PORTS_FROM",
    "CaptureInbox",
    "CaptureLink",
    "CapturePublisher",
    "ConnectionWatch",
    "Link",
    "Publisher",
    "Receiver",
    "Sender",
    "Subscriber",
    "free_loopback_ports",
    "last_endpoint",
    "link_health",
    "make_context",
]

log = logging.getLogger(__name__)

# Plain ints: pyzmq's constants are IntFlag members, and ``int & flag`` runs
# the enum's Python-level __rand__, which builds a new member on every call.
_EVENTS, _POLLIN, _NOBLOCK = int(zmq.EVENTS), int(zmq.POLLIN), int(zmq.NOBLOCK)
_RCVMORE = int(zmq.RCVMORE)


def _open(
    ctx: zmq.Context, kind: int, endpoint: str, bind: bool, opts: dict[int, Any]
) -> zmq.Socket:
    sock = ctx.socket(kind)
    sock.setsockopt(zmq.LINGER, 0)
    for opt, value in opts.items():
        sock.setsockopt(opt, value)
    try:
        if bind:
            sock.bind(endpoint)
        else:
            sock.connect(endpoint)
    except zmq.ZMQError as e:
        sock.close(0)
        verb = "bind to" if bind else "connect to"
        hint = " (is another process using this port?)" if bind else ""
        raise LinkError(f"cannot {verb} {endpoint}: {e}{hint}") from None
    return sock


def last_endpoint(sock: zmq.Socket) -> str:
    return sock.getsockopt(zmq.LAST_ENDPOINT).decode()


class _Reconnecting:
    """What ``Publisher`` and ``Subscriber`` share: a socket that can be opened again."""

    sock: zmq.Socket
    watch: ConnectionWatch | None
    link_name: str

    def _setup(
        self,
        ctx: zmq.Context,
        kind: int,
        endpoint: str,
        bind: bool,
        opts: dict[int, Any],
        reconnect: bool,
    ) -> None:
        self._args = (ctx, kind, endpoint, bind, opts)
        self.sock = _open(*self._args)
        self.watch = ConnectionWatch(self.sock, self.link_name) if reconnect and not bind else None

    def check_link(self, now: int | None = None) -> bool:
        """Open the socket again if libzmq gave up on its connection; True if it did."""
        watch = self.watch
        if watch is None or watch.closed or not watch.poll(now_ns() if now is None else now):
            return False
        log.warning(
            "%s link to %s %s and libzmq will not reconnect (a protocol error: an oversized "
            "or malformed frame, or a handshake that failed); opening the socket again",
            self.link_name,
            self._args[2],
            watch.ended_how,
        )
        old = self.sock
        watch.close(old)
        self._before_reopen(old)
        old.close(0)
        self.sock = _open(*self._args)
        self.watch = ConnectionWatch(
            self.sock,
            self.link_name,
            watch.reopens + 1,
            min(RECONNECT_MAX_S, 2 * watch.wait_s + RECONNECT_GRACE_S),
        )
        self._after_reopen()
        return True

    def _before_reopen(self, old: zmq.Socket) -> None:
        pass

    def _after_reopen(self) -> None:
        pass

    def health(self) -> dict[str, float]:
        """``link_NAME_up`` (1/0) and ``link_NAME_reopened``: what a heartbeat carries."""
        if self.watch is None:  # read only: also asked after close (a node's last stats)
            return {}
        return {
            f"link_{self.link_name}_up": float(self.watch.up),
            f"link_{self.link_name}_reopened": float(self.watch.reopens),
        }

    def close(self) -> None:
        if self.watch is not None:
            self.watch.close(self.sock)
            self.watch.closed = True
        self.sock.close(0)


def link_health(*ends: Any) -> dict[str, float]:
    """Each watched end's state and reopen count (an end with no watch says nothing)."""
    out: dict[str, float] = {}
    for end in ends:
        health = getattr(end, "health", None)  # a watched ZeroMQ socket, a fabric end
        if health is not None:
            out.update(health())
    return out


class Publisher(_Reconnecting):
    """Sends messages; a PUB never blocks, and drops for a subscriber that lags.

    ``name``: a robot's name, carried after every topic (docs/protocol.md) so
    that one path can carry several robots. ``signer``: every message is
    signed (common/wire/signing.py).
    """

    def __init__(
        self,
        ctx: zmq.Context,
        endpoint: str,
        *,
        bind: bool,
        sndhwm: int = 64,
        sock_opts: dict[int, Any] | None = None,
        name: bytes = b"",
        signer: Any = None,
        reconnect: bool = False,
        link_name: str = "telemetry",
    ) -> None:
        """``reconnect``: a connecting socket opened again when libzmq gives up on it
        (``check_link``, called by ``send`` and ``read_subscriptions``)."""
        opts = {zmq.SNDHWM: sndhwm, **(sock_opts or {})}
        self.link_name = link_name
        self._setup(ctx, zmq.PUB, endpoint, bind, opts, reconnect)
        self.endpoint = last_endpoint(self.sock) if bind else endpoint
        self.name = name
        self.signer = signer
        self.sent = 0
        self.bytes_sent = 0

    def send(self, msg: Message) -> bytes:
        data = encode(msg, self.name, self.signer)
        self.send_raw(data)
        return data

    def read_subscriptions(self) -> bool:
        """A PUB cannot tell who listens: True only when a connecting socket was opened
        again (``check_link``)."""
        return self.watch is not None and self.check_link()

    def wanted(self, prefix: bytes) -> bool:
        """Does anyone want frames starting with ``prefix``? A PUB cannot tell: always True."""
        return True

    def send_raw(self, data: bytes) -> None:
        if self.watch is not None:
            self.check_link()
        try:
            self.sock.send(data, _NOBLOCK)
        except zmq.Again:  # only for exotic socket options; a PUB drops instead
            return
        self.sent += 1
        self.bytes_sent += len(data)


class Subscriber(_Reconnecting):
    """Receives and validates messages; bad ones are counted and dropped."""

    def __init__(
        self,
        ctx: zmq.Context,
        endpoint: str,
        *,
        bind: bool,
        rcvhwm: int = 256,
        sock_opts: dict[int, Any] | None = None,
        name: str = "subscriber",
        topics: tuple[bytes, ...] = (b"",),
        expect_name: bytes | None = None,
        reconnect: bool = False,
        link_name: str = "commands",
    ) -> None:
        """``topics``: subscription prefixes (``codec.name_prefix``), b"" for everything.

        ``expect_name``: a robot name every message must carry (b"" for none);
        another is refused as ``WrongRobotError``. None accepts any.
        ``reconnect``: a connecting socket opened again when libzmq gives up on
        it (``check_link``, called by ``ready``/``poll``).
        """
        opts = {zmq.RCVHWM: rcvhwm, zmq.MAXMSGSIZE: MAX_MESSAGE_BYTES, **(sock_opts or {})}
        self.link_name = link_name
        self.topics = topics
        self._setup(ctx, zmq.SUB, endpoint, bind, opts, reconnect)
        for topic in topics:
            self.sock.setsockopt(zmq.SUBSCRIBE, topic)
        self.expect_name = expect_name
        self.endpoint = last_endpoint(self.sock) if bind else endpoint
        self.poller = zmq.Poller()
        self.poller.register(self.sock, zmq.POLLIN)
        self.received = 0
        self.rejected: Counter[str] = Counter()
        self._bad = BurstLog(log, f"{name}: rejected message")

    def poll(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for something to read."""
        return bool(self.ready(timeout_s))

    def ready(self, timeout_s: float) -> dict[Any, int]:
        """Wait up to ``timeout_s``; what is readable: this socket and any fd registered beside it.

        The wait is rounded up to ZeroMQ's whole milliseconds. Rounded down,
        the last millisecond before every deadline became a busy loop of
        zero-length polls (about 90 turns per deadline, 3 % of a core at 60 Hz).
        """
        if self.watch is not None:
            self.check_link()
        return dict(self.poller.poll(math.ceil(max(0.0, timeout_s) * 1000)))

    def _before_reopen(self, old: zmq.Socket) -> None:
        self.poller.unregister(old)

    def _after_reopen(self) -> None:
        for topic in self.topics:
            self.sock.setsockopt(zmq.SUBSCRIBE, topic)
        self.poller.register(self.sock, zmq.POLLIN)

    def drain(
        self, max_messages: int = 1024, wires: list[bytes] | None = None
    ) -> list[tuple[Message, int]]:
        """Every valid queued message with its local receive time, oldest first.

        ``wires``: each returned message's bytes as received are appended to it,
        in the same order (a recorder keeps what crossed the link, not a re-encoding).
        """
        out: list[tuple[Message, int]] = []
        sock = self.sock
        for _ in range(max_messages):
            # Ask before reading: an empty socket answers a NOBLOCK recv with an
            # exception, which costs more than the check on every loop turn.
            if not sock.get(_EVENTS) & _POLLIN:
                break
            try:
                data = sock.recv(_NOBLOCK, copy=True)
            except zmq.Again:
                break
            t_recv = now_ns()
            self.received += 1
            try:
                if sock.get(_RCVMORE):
                    parts = 1 + self._discard_rest()
                    raise MultipartMessageError(f"a message of {parts} frames (one is the rule)")
                robot, msg = decode_named(data)
                if self.expect_name is not None and robot != self.expect_name:
                    raise WrongRobotError(f"for robot {robot!r}, not {self.expect_name!r}")
                out.append((msg, t_recv))
                if wires is not None:
                    wires.append(data)
            except DecodeError as e:
                self.rejected[type(e).__name__] += 1
                self._bad(str(e))
        return out

    def _discard_rest(self) -> int:
        """Read and drop the remaining frames of a multipart message (they arrive together)."""
        n = 0
        while True:
            self.sock.recv(_NOBLOCK, copy=False)
            n += 1
            if not self.sock.get(_RCVMORE):
                return n

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())


def make_context() -> zmq.Context:
    """A fresh context per node (never the global instance), so tests can run nodes side by side."""
    return zmq.Context()
