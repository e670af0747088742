"""ZeroMQ sockets for the link between the nodes.

Freshness over completeness: a subscriber drains everything queued and the
caller keeps the newest message of each kind, so a backlog never turns into
lag. Every socket has LINGER 0 (closing never blocks), a maximum message size
(oversized frames are dropped by ZeroMQ before they are read) and bounded
queues. Decoding errors are counted by class and logged once per burst.

A connecting socket may watch its connection (``reconnect=True``): libzmq
never reconnects after a protocol error (an oversized or malformed frame from
the peer, a handshake in a language it does not speak), so such a socket is
closed and opened again by the next call that touches it, within a fraction
of a second, and says so in ``link_health``.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import math
from collections import Counter
from dataclasses import dataclass
from typing import Any, Protocol

import zmq

from common.clock import now_ns
from common.codec import (
    MAX_MESSAGE_BYTES,
    DecodeError,
    MultipartMessageError,
    WrongRobotError,
    decode_named,
    encode,
)
from common.errors import LinkError
from common.logs import BurstLog
from common.messages import Message

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


_WATCHED_EVENTS = (
    zmq.EVENT_CONNECTED
    | zmq.EVENT_CONNECT_DELAYED
    | zmq.EVENT_CONNECT_RETRIED
    | zmq.EVENT_DISCONNECTED
    | zmq.EVENT_HANDSHAKE_SUCCEEDED
    | zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL
    | zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL
    | zmq.EVENT_HANDSHAKE_FAILED_AUTH
)
#: libzmq retries at once after an ordinary disconnect (CONNECT_RETRIED); without that word
#: for this long after a disconnect or a failed handshake, it has given up on the connection
RECONNECT_GRACE_S = 0.25
#: the wait before opening again doubles while the new socket fails too, up to this
RECONNECT_MAX_S = 0.5


class ConnectionWatch:
    """A connecting socket's connection as its monitor tells it, and whether libzmq gave up.

    ``poll`` reads the queued events without waiting; it answers True when the
    connection ended (disconnect or failed handshake) and libzmq has not
    announced a retry within the grace time: the caller then opens the socket
    again. A live or retrying connection is left alone.
    """

    def __init__(self, sock: zmq.Socket, what: str, reopens: int = 0, wait_s: float = 0.0):
        self.what = what
        self.monitor = sock.get_monitor_socket(_WATCHED_EVENTS)
        self.up = False
        self.reopens = reopens
        #: when libzmq stopped trying (a disconnect or failed handshake not followed by a retry)
        self._ended_ns: int | None = None
        self._ended_how = ""
        self.wait_s = wait_s  # before reopening: grows while reopened sockets fail too
        self.closed = False  # the socket's owner closed it: nothing to watch any more

    def poll(self, now: int) -> bool:
        from zmq.utils.monitor import recv_monitor_message

        mon = self.monitor
        while mon.get(_EVENTS) & _POLLIN:
            try:
                event = recv_monitor_message(mon, _NOBLOCK)["event"]
            except zmq.Again:
                break
            if event == zmq.EVENT_HANDSHAKE_SUCCEEDED:
                self.up, self._ended_ns, self.wait_s = True, None, 0.0
            elif event in (zmq.EVENT_CONNECT_RETRIED, zmq.EVENT_CONNECT_DELAYED):
                self._ended_ns = None  # libzmq carries on by itself
            elif event != zmq.EVENT_CONNECTED:  # a disconnect, or a handshake that failed
                self.up = False
                self._ended_ns = now
                self._ended_how = "closed" if event == zmq.EVENT_DISCONNECTED else "refused"
        if self._ended_ns is None:
            return False
        return now - self._ended_ns >= (RECONNECT_GRACE_S + self.wait_s) * 1e9

    def close(self, sock: zmq.Socket) -> None:
        with contextlib.suppress(zmq.ZMQError):  # already closed
            sock.disable_monitor()
        self.monitor.close(0)


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
            watch._ended_how,
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
    signed (common/signing.py).
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


class Sender(Protocol):
    """The sending half of a node's link (``Publisher``, ``CapturePublisher``)."""

    sent: int

    def send(self, msg: Message) -> bytes: ...

    def close(self) -> None: ...


class Receiver(Protocol):
    """The receiving half of a node's link (``Subscriber``, ``CaptureInbox``)."""

    def poll(self, timeout_s: float) -> bool: ...

    def drain(
        self, max_messages: int = 1024, wires: list[bytes] | None = None
    ) -> list[tuple[Message, int]]: ...

    @property
    def rejected_total(self) -> int: ...

    def close(self) -> None: ...


@dataclass
class Link:
    """What a node sends on (``pub``) and reads from (``sub``).

    A node opens its ZeroMQ link in ``run()``; one handed a link instead is
    driven by its caller (``process``, ``receive``, ``palm_step``): the
    bench, replay and tests, with real sockets or a ``CaptureLink``. A half
    the caller does not need may be None.
    """

    pub: Sender | None = None
    sub: Receiver | None = None


class CapturePublisher:
    """A ``Publisher`` with no socket: keeps every message, and encodes it as the socket would."""

    endpoint = "capture://"

    def __init__(self) -> None:
        self.messages: list[Message] = []
        self.sent = 0
        self.bytes_sent = 0

    def send(self, msg: Message) -> bytes:
        data = encode(msg)
        self.messages.append(msg)
        self.sent += 1
        self.bytes_sent += len(data)
        return data

    def close(self) -> None:
        pass


class CaptureInbox:
    """A ``Subscriber`` with no socket: hands out what ``deliver`` queued, oldest first."""

    endpoint = "capture://"

    def __init__(self) -> None:
        self._queue: collections.deque[tuple[Message, int]] = collections.deque()
        self.received = 0
        self.rejected: Counter[str] = Counter()

    def deliver(self, msg: Message, t_recv_ns: int) -> None:
        self._queue.append((msg, t_recv_ns))

    def poll(self, timeout_s: float) -> bool:
        return bool(self._queue)

    def drain(
        self, max_messages: int = 1024, wires: list[bytes] | None = None
    ) -> list[tuple[Message, int]]:
        """``wires``: each message encoded as a socket would carry it (unsigned, unnamed)."""
        out = []
        while self._queue and len(out) < max_messages:
            out.append(self._queue.popleft())
            if wires is not None:
                wires.append(encode(out[-1][0]))
        self.received += len(out)
        return out

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())

    def close(self) -> None:
        self._queue.clear()


class CaptureLink(Link):
    """A link in memory: what the node sends is kept in ``messages``; ``deliver`` feeds it."""

    pub: CapturePublisher
    sub: CaptureInbox

    def __init__(self) -> None:
        super().__init__(pub=CapturePublisher(), sub=CaptureInbox())

    @property
    def messages(self) -> list[Message]:
        return self.pub.messages

    def deliver(self, msg: Message, t_recv_ns: int) -> None:
        self.sub.deliver(msg, t_recv_ns)


#: Where ports known in advance are drawn: from here up to the kernel's ephemeral range.
KNOWN_PORTS_FROM = 10000


def _ephemeral_low(path: str = "/proc/sys/net/ipv4/ip_local_port_range") -> int | None:
    """The lowest port the kernel hands out on its own (a bind to port 0, a connect)."""
    try:
        with open(path) as f:
            return int(f.read().split()[0])
    except (OSError, ValueError, IndexError):
        return None


def free_loopback_ports(n: int, host: str = "127.0.0.1", *, udp: bool = False) -> list[int]:
    """``n`` TCP ports free on ``host`` right now (for endpoints that must be known in advance).

    Drawn at random below the kernel's ephemeral range: a port there can only be taken by a
    process that names it. A port the kernel picked itself (a bind to port 0) was free only
    until the probe closed it: any process's next bind to port 0, or an outgoing
    connection's source port, could take it before the caller bound it (a robot node's
    bind failed that way beside two other deployments). Each port is bound once here to
    check that nothing listens on it. Where the range leaves no room below it, the kernel
    picks. ``udp``: UDP ports (a QUIC listener's), checked by a UDP bind.
    """
    import random
    import socket

    low = _ephemeral_low()
    room = low is not None and low - KNOWN_PORTS_FROM >= 1000
    draws = random.SystemRandom()
    socks: list[socket.socket] = []
    try:
        for _ in range(100 * n):
            if len(socks) == n:
                break
            s = socket.socket(type=socket.SOCK_DGRAM if udp else socket.SOCK_STREAM)
            try:
                s.bind((host, draws.randrange(KNOWN_PORTS_FROM, low) if room else 0))
            except OSError:  # in use (or in TIME_WAIT): draw again
                s.close()
                if not room:
                    raise
                continue
            socks.append(s)
        if len(socks) < n:
            raise OSError(f"no {n} free ports on {host} in {KNOWN_PORTS_FROM}..{low - 1}")
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()


def make_context() -> zmq.Context:
    """A fresh context per node (never the global instance), so tests can run nodes side by side."""
    return zmq.Context()
