"""The stream forwarder's pipes: each direction of each forwarded connection.

A pipe reads what one ``recv`` returns (the forwarder's stand-in for a
packet, timed from the kernel's receive timestamp), asks its direction's
impairment engine when the chunk may leave, and sends it then; what the
receiver has not taken waits in ``pending``. A chunk whose delay is zero is
sent as soon as it is read. A connection closed on either side (or reset
after repeated losses) closes both of its pipes, keeping their engines'
counts.
"""

from __future__ import annotations

import logging
import socket
import time
from collections import deque

from common.netsim.impairments import DIRECTIONS, DirectionImpairment
from common.netsim.kernel_stamps import ANC_BYTES, arrival_ns
from common.netsim.proxy import DirectionCounters

log = logging.getLogger(__name__)

RECV_BYTES = 1 << 16


class Pipe:
    """One direction of one forwarded connection."""

    __slots__ = (
        "closed",
        "counters",
        "direction",
        "dst",
        "engine",
        "pending",
        "queue",
        "src",
    )

    def __init__(
        self,
        src: socket.socket,
        dst: socket.socket,
        direction: str,
        engine: DirectionImpairment | None,
        counters: DirectionCounters,
    ) -> None:
        self.src = src
        self.dst = dst
        self.direction = direction
        self.engine = engine  # None: passthrough
        self.counters = counters
        #: (due ns, arrival ns, bytes), in due order.
        self.queue: deque[tuple[int, int, bytes]] = deque()
        self.pending = bytearray()  # released but not yet accepted by the kernel
        self.closed = False


class StreamPipes:
    """Every open pipe, the engines behind them, and what the forwarding cost.

    ``dirty``: the set of pipes, or of blocked receivers, changed since the
    forwarder last built its select lists.
    """

    def __init__(self) -> None:
        self.pipes: list[Pipe] = []
        self.engines: list[DirectionImpairment] = []
        #: Counts of the engines of connections already closed, per direction.
        self.retired: dict[str, dict[str, int]] = {name: {} for name in DIRECTIONS}
        self.dirty = True
        #: recent per-chunk costs: sent minus the later of arrival and due time
        self.own_ns: deque[int] = deque(maxlen=100_000)

    def add(self, pipe: Pipe) -> None:
        if pipe.engine is not None:
            self.engines.append(pipe.engine)
        self.pipes.append(pipe)
        self.dirty = True

    def close_all(self) -> None:
        for pipe in self.pipes:
            for s in (pipe.src, pipe.dst):
                s.close()
        self.pipes = []

    def close_pair(self, pipe: Pipe) -> None:
        """Close both directions of the connection ``pipe`` belongs to (as a reset would)."""
        socks = {pipe.src, pipe.dst}
        for p in self.pipes:
            if p.src in socks:
                p.closed = True
                if p.engine is not None:  # keep its counts, not the engine
                    retired = self.retired[p.direction]
                    for key, value in p.engine.counts.as_dict().items():
                        retired[key] = retired.get(key, 0) + value
                    self.engines.remove(p.engine)
        for s in socks:
            s.close()
        self.pipes = [p for p in self.pipes if not p.closed]
        self.dirty = True

    def read(self, pipe: Pipe, real_minus_mono: int) -> None:
        try:
            data, anc, _, _ = pipe.src.recvmsg(RECV_BYTES, ANC_BYTES)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data, anc = b"", []
        if pipe.engine is None and data and not pipe.pending:
            # Nothing to simulate: out first, accounting after.
            try:
                sent = pipe.dst.send(data)
            except (BlockingIOError, InterruptedError):
                sent = 0
            except OSError:
                self.close_pair(pipe)
                return
            t_sent = time.monotonic_ns()
            if sent < len(data):
                pipe.pending += data[sent:]
                self.dirty = True
            arrival = arrival_ns(anc, t_sent, real_minus_mono)
            c = pipe.counters
            c.received += 1
            c.sent += 1
            c.bytes_in += len(data)
            c.bytes_out += len(data)
            self.own_ns.append(t_sent - arrival)
            return
        t_read = time.monotonic_ns()
        if not data:  # the peer closed (or reset): pass the close on
            self.close_pair(pipe)
            return
        arrival = arrival_ns(anc, t_read, real_minus_mono)
        c = pipe.counters
        c.received += 1
        c.bytes_in += len(data)
        if pipe.engine is None:
            self.release(pipe, data, arrival, arrival)
            return
        out = pipe.engine.process(arrival, data)
        if not out:  # gave up after the retransmissions: TCP resets the connection
            c.dropped += 1
            log.warning("netsim: %s connection reset after repeated losses", pipe.direction)
            self.close_pair(pipe)
            return
        due, payload = out[0]
        if not pipe.queue and due <= t_read:
            self.release(pipe, payload, arrival, due)
        else:
            pipe.queue.append((due, arrival, payload))

    def release(self, pipe: Pipe, data: bytes, arrival: int, due: int) -> None:
        """Send ``data`` (or queue it behind what the receiver has not taken yet)."""
        if pipe.pending:
            pipe.pending += data
        else:
            try:
                sent = pipe.dst.send(data)
            except (BlockingIOError, InterruptedError):
                sent = 0
            except OSError:
                self.close_pair(pipe)
                return
            if sent < len(data):
                pipe.pending += data[sent:]
                self.dirty = True
        t1 = time.monotonic_ns()
        c = pipe.counters
        c.sent += 1
        c.bytes_out += len(data)
        start = due if due > arrival else arrival
        self.own_ns.append(t1 - start)
        late = t1 - due
        if late > c.late_ns_max:
            c.late_ns_max = late

    def flush(self, pipe: Pipe) -> None:
        try:
            sent = pipe.dst.send(pipe.pending)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self.close_pair(pipe)
            return
        del pipe.pending[:sent]
        if not pipe.pending:
            self.dirty = True
