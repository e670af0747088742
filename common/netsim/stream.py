"""The stream mode: each direction's TCP byte stream forwarded unchanged.

ZeroMQ's wire protocol (ZMTP), CURVE's handshake and its encrypted frames
pass through untouched, so the deployed configuration (encrypted,
allowlisted) runs under impairments. The forwarder never parses a byte; it
only decides when each chunk it reads leaves, with the same engine as the
message mode (``DirectionImpairment`` in the stream delivery model): delay
with its distribution and correlation, the bottleneck rate, outages and
losses as the retransmission stalls TCP would show. A chunk is what one
``recv`` returned, the forwarder's stand-in for a packet.

Its own cost is kept out of the delays: every chunk is timed from the
kernel's receive timestamp (``SO_TIMESTAMPNS``), so the thread's wake-up
and read are inside the scheduled delay, and the thread spins the last
``spin_us`` before a due time. A send never starts before its due time: on
loopback the bytes reach the receiver inside ``send``, so starting it early
by its expected cost would deliver them early. A chunk whose delay is zero
is sent as soon as it is read, without going through the schedule.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import logging
import math
import select
import socket
import time
from typing import Any
from urllib.parse import urlsplit

from common.errors import ConfigError, LinkError
from common.netsim.impairments import DIRECTIONS, DirectionConfig, DirectionImpairment, Scenario
from common.netsim.kernel_stamps import SO_TIMESTAMPNS
from common.netsim.proxy import (
    DirectionCounters,
    Endpoints,
    ForwardingThread,
    set_timer_slack_ns,
)
from common.netsim.stream_pipes import Pipe, StreamPipes

log = logging.getLogger(__name__)

#: Longest the thread sleeps before checking for ``stop()``.
_MAX_WAIT_S = 0.02
#: Bytes waiting for a slow receiver before the forwarder stops reading its source.
_BACKPRESSURE_BYTES = 1 << 22
#: A connection to the robot must be up within this (connects block the forwarder's thread).
_CONNECT_TIMEOUT_S = 1.0


def _host_port(endpoint: str) -> tuple[str, int]:
    """``tcp://host:port`` (port ``*`` = any free one) as a socket address."""
    parts = urlsplit(endpoint)
    if parts.scheme != "tcp" or not parts.hostname:
        raise ConfigError(f"the stream forwarder needs tcp://HOST:PORT endpoints, not {endpoint!r}")
    port_text = parts.netloc.rsplit(":", 1)[-1]
    if port_text == "*":
        return parts.hostname, 0
    try:
        return parts.hostname, int(port_text)
    except ValueError:
        raise ConfigError(f"bad port in endpoint {endpoint!r}") from None


def stream_config(config: DirectionConfig) -> DirectionConfig:
    """A direction's impairments as a byte stream can carry them.

    A forwarder cannot drop or damage bytes without breaking the TCP stream it
    stands for (TCP's checksum and flow control prevent both), so datagram
    delivery is refused, corruption is left to the message mode, and a full
    bottleneck queue holds the sender back instead of dropping.
    """
    if config.delivery != "stream":
        raise ConfigError(
            "delivery = 'datagram' needs the message mode (mode = 'message'): a byte-stream "
            "forwarder cannot lose, duplicate or reorder what TCP delivers"
        )
    return dataclasses.replace(config, corrupt_percent=0.0, queue_limit=1 << 30)


def _is_passthrough(config: DirectionConfig) -> bool:
    """No impairment at all: every chunk leaves the moment it is read."""
    return (
        config.delay_ms == 0
        and config.distribution != "table"
        and config.jitter_ms == 0
        and config.loss_rate() == 0
        and config.rate_kbit == 0
        and not config.outages
        and not config.trace_file
    )


class StreamForwarder(ForwardingThread):
    """Forwards the robot's two TCP links, each direction impaired by ``scenario``.

    The operator connects to ``operator_telemetry_endpoint`` and
    ``operator_commands_endpoint`` (resolved after ``start()``); each
    connection gets its own to the robot's endpoint. Bytes from the robot
    are ``to_operator``, bytes to it ``to_robot``, on both links (the
    telemetry link's ``to_robot`` bytes are ZMTP's handshake and
    subscriptions). Same interface as ``LinkSimulator``.
    """

    thread_name = "netsim-stream"

    def __init__(
        self,
        scenario: Scenario | None = None,
        *,
        endpoints: Endpoints | None = None,
        seed: int = 0,
        spin_us: float = 300.0,
    ) -> None:
        self.scenario = scenario if scenario is not None else Scenario()
        self.endpoints = endpoints if endpoints is not None else Endpoints()
        self.seed = seed
        if spin_us < 0:
            raise ConfigError(f"spin_us must be >= 0, not {spin_us}")
        self.spin_ns = round(spin_us * 1000)
        self._configs = {name: stream_config(self.scenario.direction(name)) for name in DIRECTIONS}
        self._passthrough = {name: _is_passthrough(c) for name, c in self._configs.items()}
        self._counters = {name: DirectionCounters() for name in DIRECTIONS}
        self._connections = 0
        self._unreachable: set[str] = set()
        self._spun = 0  # reads found while spinning (ahead of a release or a chunk)
        self._listeners: list[tuple[str, socket.socket, tuple[str, int]]] = []
        #: each direction of each forwarded connection
        self.pipes = StreamPipes()
        self._init_thread()
        self.start_ns: int | None = None
        self.operator_telemetry_endpoint: str | None = None
        self.operator_commands_endpoint: str | None = None

    # ------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Bind the operator-side listeners and start forwarding."""
        if self._thread is not None:
            raise LinkError("StreamForwarder.start() called twice")
        ep = self.endpoints
        links = (
            ("telemetry", ep.operator_telemetry, ep.robot_telemetry),
            ("commands", ep.operator_commands, ep.robot_commands),
        )
        for name, bind_at, robot_at in links:
            host, port = _host_port(bind_at)
            target = _host_port(robot_at)
            try:
                listener = socket.create_server((host, port), reuse_port=False)
            except OSError as e:
                self._close_listeners()
                raise LinkError(f"netsim cannot bind to {bind_at}: {e}") from None
            listener.setblocking(False)
            self._listeners.append((name, listener, target))
        tel, cmd = (lst.getsockname() for _, lst, _ in self._listeners)
        self.operator_telemetry_endpoint = f"tcp://{tel[0]}:{tel[1]}"
        self.operator_commands_endpoint = f"tcp://{cmd[0]}:{cmd[1]}"
        self.start_ns = time.monotonic_ns()
        self._launch()
        log.info(
            "netsim %r (byte stream): robot %s / %s <-> operator %s / %s",
            self.scenario.name,
            ep.robot_telemetry,
            ep.robot_commands,
            self.operator_telemetry_endpoint,
            self.operator_commands_endpoint,
        )

    # ------------------------------------------------------------ state
    def counters(self) -> dict[str, dict[str, Any]]:
        """Per direction: chunks and bytes forwarded, and the impairments' counts by cause."""
        out: dict[str, dict[str, Any]] = {}
        for name in DIRECTIONS:
            row: dict[str, Any] = self._counters[name].as_dict()
            for key, value in dict(self.pipes.retired[name]).items():
                row[key] = row.get(key, 0) + value
            for engine in list(self.pipes.engines):
                if engine.name.startswith(name):
                    for key, value in engine.counts.as_dict().items():
                        row[key] = row.get(key, 0) + value
            out[name] = row
        return out

    def connection_counts(self) -> dict[str, int]:
        """Connections forwarded so far, and reads found while spinning before a release."""
        return {"connections": self._connections, "reads_while_spinning": self._spun}

    def own_latency_ns(self) -> list[int]:
        """Recent per-chunk costs of the forwarder: sent minus the later of arrival and due time."""
        return list(self.pipes.own_ns)

    # ------------------------------------------------------------ connections
    def _accept(self, link: str, listener: socket.socket, target: tuple[str, int]) -> None:
        try:
            client, _ = listener.accept()
        except BlockingIOError:
            return
        try:
            upstream = socket.create_connection(target, timeout=_CONNECT_TIMEOUT_S)
        except OSError as e:
            if link not in self._unreachable:  # once until it works: ZeroMQ retries often
                self._unreachable.add(link)
                log.warning("netsim: robot %s link %s:%d unreachable: %s", link, *target, e)
            client.close()
            return
        self._unreachable.discard(link)
        self._connections += 1
        n = self._connections
        for sock in (client, upstream):
            sock.setblocking(False)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            # Without receive timestamps, chunks are timed when read.
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        for src, dst, direction in (
            (upstream, client, "to_operator"),
            (client, upstream, "to_robot"),
        ):
            engine = None
            if not self._passthrough[direction]:
                assert self.start_ns is not None
                engine = DirectionImpairment(
                    self._configs[direction],
                    seed=self.seed,
                    name=f"{direction}:{link}:{n}",
                    start_ns=self.start_ns,
                    cuts=self.cuts,
                )
            self.pipes.add(Pipe(src, dst, direction, engine, self._counters[direction]))
        log.debug("netsim: %s connection %d forwarded to %s:%d", link, n, *target)

    def _close_listeners(self) -> None:
        for _, listener, _ in self._listeners:
            listener.close()
        self._listeners = []

    # ------------------------------------------------------------ the loop
    def _run(self) -> None:
        set_timer_slack_ns(1_000)
        now_ns = time.monotonic_ns
        spin_ns = self.spin_ns
        stop = self._stop
        readers: list[Any] = []
        writers: list[Any] = []
        by_sock: dict[Any, Pipe] = {}
        pipes = self.pipes
        try:
            while not stop.is_set():
                if pipes.dirty:  # connections or blocked receivers changed
                    pipes.dirty = False
                    readers = [lst for _, lst, _ in self._listeners]
                    writers = [p.dst for p in pipes.pipes if p.pending]
                    by_sock = {}
                    for pipe in pipes.pipes:
                        if len(pipe.pending) < _BACKPRESSURE_BYTES:
                            readers.append(pipe.src)
                            by_sock[pipe.src] = pipe
                # Release what is due, in due order per pipe.
                next_ns = None
                t = now_ns()
                for pipe in pipes.pipes:
                    q = pipe.queue
                    while q and q[0][0] <= t and not pipe.closed:
                        due, arrival, data = q.popleft()
                        pipes.release(pipe, data, arrival, due)
                        t = now_ns()
                    if q and (next_ns is None or q[0][0] - spin_ns < next_ns):
                        next_ns = q[0][0] - spin_ns
                if pipes.dirty:
                    continue
                # Wait for bytes, a writable receiver, or the next release.
                wait_s = _MAX_WAIT_S
                if next_ns is not None:
                    wait_s = max(0.0, min(wait_s, (next_ns - t) / 1e9))
                readable, writable = _wait(readers, writers, wait_s)
                if readable and wait_s == 0.0:
                    self._spun += 1  # a chunk that came in while spinning for a release
                if readable:
                    real_minus_mono = time.time_ns() - now_ns()
                    for sock in readable:
                        pipe = by_sock.get(sock)
                        if pipe is not None:
                            if not pipe.closed:
                                pipes.read(pipe, real_minus_mono)
                            continue
                        for link, listener, target in self._listeners:
                            if listener is sock:
                                self._accept(link, listener, target)
                for sock in writable:
                    for pipe in pipes.pipes:
                        if pipe.dst is sock and pipe.pending and not pipe.closed:
                            pipes.flush(pipe)
        except BaseException as e:  # report, never die silently
            self._error = e
            log.exception("netsim stream forwarder stopped")
        finally:
            pipes.close_all()
            self._close_listeners()


def _wait(readers: list[Any], writers: list[Any], wait_s: float) -> tuple[list[Any], list[Any]]:
    """``select`` (microsecond timeouts) while the descriptors allow it, else ``poll``."""
    if all(s.fileno() < 1024 for s in (*readers, *writers)):
        try:
            r, w, _ = select.select(readers, writers, [], wait_s)
        except OSError as e:  # a socket closed under us: look again
            if e.errno != errno.EBADF:
                raise
            return [], []
        return r, w
    poller = select.poll()
    for s in readers:
        poller.register(s, select.POLLIN)
    for s in writers:
        poller.register(s, select.POLLOUT | (select.POLLIN if s in readers else 0))
    fds = {s.fileno(): s for s in (*readers, *writers)}
    r, w = [], []
    for fd, ev in poller.poll(math.floor(wait_s * 1000)):
        if ev & (select.POLLIN | select.POLLHUP | select.POLLERR) and fds[fd] in readers:
            r.append(fds[fd])
        if ev & select.POLLOUT:
            w.append(fds[fd])
    return r, w
