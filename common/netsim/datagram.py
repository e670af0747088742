"""The simulator for UDP: each datagram forwarded whole, late, lost, duplicated or reordered.

WebRTC media (SRTP, DTLS, ICE's STUN checks) is UDP, which the stream relay
cannot carry. This relay listens on one UDP port for the operator side's
packets and forwards them to one robot-side address; the robot's replies go
back to whoever sent to it. Every sender address gets its own socket towards
the robot (as a NAT maps each flow), so several viewers, or the several
sockets ICE tries from, stay apart. Packets towards the robot are
``to_robot``, the replies ``to_operator``, as in the stream relay.

The scenario files and traces are the stream mode's; every direction is run
in the datagram delivery model (``datagram_config``): a loss is a loss, the
bottleneck's queue tail-drops, jitter reorders unless the scenario says
``jitter_reorders = false``, and duplication and netem's reordering apply.
One engine per direction serves every flow, so the bottleneck is the link's,
shared as a real one is.

Timing follows the stream relay: each datagram is timed from the kernel's
receive timestamp, and the thread spins the last ``spin_us`` before a due
time instead of sleeping through it. A send never starts before its due
time on the relay's monotonic clock: loopback hands the datagram to its
receiver inside ``send``, so a send started early by its expected cost
would deliver it that much early. Needs no root and no kernel module.
"""

from __future__ import annotations

import contextlib
import dataclasses
import heapq
import logging
import select
import socket
import time
from collections import OrderedDict, deque
from typing import Any

from common.errors import ConfigError, LinkError
from common.netsim.impairments import DIRECTIONS, DirectionConfig, DirectionImpairment, Scenario
from common.netsim.kernel_stamps import ANC_BYTES, SO_TIMESTAMPNS, arrival_ns
from common.netsim.proxy import DirectionCounters, ForwardingThread, set_timer_slack_ns

log = logging.getLogger(__name__)

Address = tuple[str, int]

#: Longest the thread sleeps before checking for ``stop()``.
_MAX_WAIT_S = 0.02
#: Larger than any UDP payload on loopback (65,507 bytes).
_RECV_BYTES = 1 << 16
#: Datagrams read from one socket before due ones are released again.
_MAX_BATCH = 64
#: Sender addresses mapped at once; the longest idle one is forgotten beyond this.
MAX_FLOWS = 64


def datagram_config(config: DirectionConfig) -> DirectionConfig:
    """A direction's impairments as UDP meets them: lost is lost, never resent."""
    return dataclasses.replace(config, delivery="datagram")


class _Flow:
    """One operator-side sender and the socket that speaks for it towards the robot."""

    __slots__ = ("client", "upstream")

    def __init__(self, client: Address, upstream: socket.socket) -> None:
        self.client = client
        self.upstream = upstream


class DatagramForwarder(ForwardingThread):
    """Forwards UDP between senders to ``listen`` and the robot-side ``target``.

    ``start()`` binds; ``address`` is then the (host, port) the operator side
    sends to. ``start_ns`` anchors the scenario's outages (the monotonic
    clock; default: ``start()``). Same interface as the other simulators:
    ``counters()``, ``own_latency_ns()``, ``stop()``, context manager.
    """

    thread_name = "netsim-datagram"

    def __init__(
        self,
        scenario: Scenario | None = None,
        *,
        target: Address,
        listen: Address = ("127.0.0.1", 0),
        seed: int = 0,
        spin_us: float = 300.0,
        start_ns: int | None = None,
    ) -> None:
        if spin_us < 0:
            raise ConfigError(f"spin_us must be >= 0, not {spin_us}")
        self.scenario = scenario if scenario is not None else Scenario()
        self.target = target
        self.listen = listen
        self.seed = seed
        self.spin_ns = round(spin_us * 1000)
        self.start_ns = start_ns
        self.address: Address | None = None
        self._configs = {n: datagram_config(self.scenario.direction(n)) for n in DIRECTIONS}
        self._engines: dict[str, DirectionImpairment] = {}
        self._counters = {name: DirectionCounters() for name in DIRECTIONS}
        self._sock: socket.socket | None = None
        self._flows: OrderedDict[Address, _Flow] = OrderedDict()
        self._by_upstream: dict[socket.socket, _Flow] = {}
        #: (due ns, order, arrival ns, direction, flow, bytes): equal dues leave in arrival
        #: order, so a direction whose jitter must not reorder (its dues never decrease) keeps it
        self._heap: list[tuple[int, int, int, str, _Flow, bytes]] = []
        self._order = 0
        self._own_ns: deque[int] = deque(maxlen=100_000)
        self._init_thread()

    # ------------------------------------------------------------ lifecycle
    def start(self) -> None:
        if self._thread is not None:
            raise LinkError("DatagramForwarder.start() called twice")
        sock = socket.socket(_family(self.listen[0]), socket.SOCK_DGRAM)
        try:
            sock.bind(self.listen)
        except OSError as e:
            sock.close()
            raise LinkError(
                f"netsim cannot bind UDP {self.listen[0]}:{self.listen[1]}: {e}"
            ) from None
        _prepare(sock)
        self._sock = sock
        self.address = sock.getsockname()[:2]
        if self.start_ns is None:
            self.start_ns = time.monotonic_ns()
        self._engines = {
            name: DirectionImpairment(
                self._configs[name],
                seed=self.seed,
                name=f"udp:{name}",
                start_ns=self.start_ns,
                cuts=self.cuts,
            )
            for name in DIRECTIONS
        }
        self._launch()
        log.info(
            "netsim %r (datagrams): %s:%d -> %s:%d",
            self.scenario.name,
            *self.address,
            *self.target,
        )

    def _after_stop(self) -> None:
        for flow in self._flows.values():
            flow.upstream.close()
        self._flows.clear()
        self._by_upstream.clear()
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    # ------------------------------------------------------------ state
    def counters(self) -> dict[str, dict[str, Any]]:
        """Per direction: datagrams and bytes in and out, and the impairments' counts by cause."""
        out: dict[str, dict[str, Any]] = {}
        for name in DIRECTIONS:
            row: dict[str, Any] = self._counters[name].as_dict()
            engine = self._engines.get(name)
            if engine is not None:
                row.update(engine.counts.as_dict())
            out[name] = row
        out["relay"] = {"flows": len(self._flows)}
        return out

    def own_latency_ns(self) -> list[int]:
        """Recent per-datagram costs: sent minus the later of arrival and due time."""
        return list(self._own_ns)

    # ------------------------------------------------------------ the loop
    def _flow_for(self, client: Address) -> _Flow:
        flow = self._flows.get(client)
        if flow is not None:
            self._flows.move_to_end(client)
            return flow
        if len(self._flows) >= MAX_FLOWS:
            _, old = self._flows.popitem(last=False)
            del self._by_upstream[old.upstream]
            old.upstream.close()
        up = socket.socket(_family(self.target[0]), socket.SOCK_DGRAM)
        up.bind((self.listen[0], 0))
        up.connect(self.target)
        _prepare(up)
        flow = _Flow(client, up)
        self._flows[client] = flow
        self._by_upstream[up] = flow
        log.debug("netsim: UDP flow from %s:%d", *client)
        return flow

    def _read(self, sock: socket.socket, real_minus_mono: int) -> None:
        flow = None if sock is self._sock else self._by_upstream.get(sock)
        direction = "to_robot" if flow is None else "to_operator"
        counters = self._counters[direction]
        engine = self._engines[direction]
        for _ in range(_MAX_BATCH):
            try:
                data, anc, _, sender = sock.recvmsg(_RECV_BYTES, ANC_BYTES)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:  # ICMP unreachable from an earlier send: nothing to read
                continue
            t_read = time.monotonic_ns()
            arrival = arrival_ns(anc, t_read, real_minus_mono)
            counters.received += 1
            counters.bytes_in += len(data)
            out_flow = flow if flow is not None else self._flow_for(sender[:2])
            deliveries = engine.process(arrival, data)
            if not deliveries:
                counters.dropped += 1
                continue
            counters.duplicated += len(deliveries) - 1
            for due, payload in deliveries:
                if due <= t_read and not self._heap:
                    self._send(direction, out_flow, payload, arrival, due)
                else:
                    heapq.heappush(
                        self._heap, (due, self._order, arrival, direction, out_flow, payload)
                    )
                    self._order += 1

    def _send(self, direction: str, flow: _Flow, data: bytes, arrival: int, due: int) -> None:
        """Send one datagram; called only once its due time has come."""
        try:
            if direction == "to_robot":
                flow.upstream.send(data)
            else:
                assert self._sock is not None
                self._sock.sendto(data, flow.client)
        except OSError:  # a full socket buffer or a closed port: lost, as UDP is
            self._counters[direction].dropped += 1
            return
        t1 = time.monotonic_ns()
        c = self._counters[direction]
        c.sent += 1
        c.bytes_out += len(data)
        self._own_ns.append(t1 - max(due, arrival))
        late = t1 - due
        if late > c.late_ns_max:
            c.late_ns_max = late

    def _run(self) -> None:
        set_timer_slack_ns(1_000)
        now_ns = time.monotonic_ns
        heap = self._heap
        stop = self._stop
        try:
            while not stop.is_set():
                t = now_ns()
                while heap and heap[0][0] <= t:
                    due, _, arrival, direction, flow, data = heapq.heappop(heap)
                    if direction == "to_robot" and flow.upstream.fileno() < 0:
                        continue  # its flow was forgotten meanwhile
                    self._send(direction, flow, data, arrival, due)
                    t = now_ns()
                wait_s = _MAX_WAIT_S
                if heap:
                    wait_s = max(0.0, min(wait_s, (heap[0][0] - self.spin_ns - t) / 1e9))
                assert self._sock is not None
                readers = [self._sock, *self._by_upstream]
                readable, _, _ = select.select(readers, [], [], wait_s)
                if readable:
                    real_minus_mono = time.time_ns() - now_ns()
                    for sock in readable:
                        self._read(sock, real_minus_mono)
        except BaseException as e:  # report, never die silently
            self._error = e
            log.exception("netsim datagram relay stopped")


def _family(host: str) -> socket.AddressFamily:
    return socket.AF_INET6 if ":" in host else socket.AF_INET


def _prepare(sock: socket.socket) -> None:
    sock.setblocking(False)
    with contextlib.suppress(OSError):  # without it, datagrams are timed when read
        sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    with contextlib.suppress(OSError):  # room for a burst of video packets
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
