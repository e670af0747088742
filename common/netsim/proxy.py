"""The simulator on the wire: ZeroMQ in, impaired schedule, ZeroMQ out.

Both directions run in one background thread that owns all four sockets
(ZeroMQ sockets are not thread-safe). Messages are forwarded as raw bytes,
never decoded: the simulator must not depend on, or hide bugs in, the codec.

Scheduling is what makes the delays trustworthy: every delivery goes into a
heap keyed by its due time on the monotonic clock, and the thread waits on
the input sockets' file descriptors with ``select`` and a timeout that ends
just before the next due time (``select`` takes microseconds, ``zmq.Poller``
only milliseconds), then spins the last ``spin_us`` so the release is not
delayed by a cold wake-up.
"""

from __future__ import annotations

import heapq
import logging
import math
import select
import threading
import time
from abc import ABC, abstractmethod
from collections import deque
from dataclasses import dataclass
from typing import Any, Self

import zmq

from common.config.typed import param
from common.errors import ConfigError, LinkError
from common.netsim.impairments import DIRECTIONS, DirectionImpairment, LinkCuts, Scenario

log = logging.getLogger(__name__)

#: Longest the thread sleeps before checking for ``stop()``.
_MAX_WAIT_S = 0.02
#: Reads per socket before due messages are released, so a flood cannot delay them.
_MAX_BATCH = 256
#: Frames above this are dropped by ZeroMQ before they reach the simulator.
_MAX_MESSAGE_BYTES = 1 << 20


@dataclass
class Endpoints:
    """Where the simulator connects (robot side) and binds (operator side)."""

    robot_telemetry: str = param(
        "tcp://127.0.0.1:5555", "the robot's bound telemetry PUB; a SUB connects to it"
    )
    robot_commands: str = param(
        "tcp://127.0.0.1:5556", "the robot's bound command SUB; a PUB connects to it"
    )
    operator_telemetry: str = param(
        "tcp://127.0.0.1:5565", "bound PUB the operator's telemetry SUB connects to"
    )
    operator_commands: str = param(
        "tcp://127.0.0.1:5566", "bound SUB the operator's command PUB connects to"
    )


@dataclass
class DirectionCounters:
    """What happened to one direction's messages since ``start()``."""

    received: int = 0  # messages read from the input socket
    sent: int = 0  # deliveries written to the output socket (duplicates included)
    dropped: int = 0  # messages for which the impairment returned no delivery
    duplicated: int = 0  # extra deliveries beyond one per message
    bytes_in: int = 0
    bytes_out: int = 0
    late_ns_max: int = 0  # worst lateness of a send past its due time

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def set_timer_slack_ns(ns: int) -> None:
    """Ask Linux to wake this thread on time (default slack is 50 us); best effort."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        pr_set_timerslack = 29
        libc.prctl(pr_set_timerslack, ctypes.c_ulong(ns), 0, 0, 0)
    except (OSError, AttributeError):  # not Linux: keep the default slack
        pass


class _Direction:
    __slots__ = ("counters", "engine", "fd", "name", "rx", "tx")

    def __init__(self, name: str, rx: zmq.Socket, tx: zmq.Socket, engine: DirectionImpairment):
        self.name = name
        self.rx = rx
        self.tx = tx
        self.engine = engine
        self.fd = rx.getsockopt(zmq.FD)
        self.counters = DirectionCounters()


class ForwardingThread(ABC):
    """One background thread that forwards until stopped: either mode's life.

    A subclass sets up its sockets in ``start`` and then calls :meth:`_launch`;
    ``_run`` stores what ended it in ``_error``; :meth:`_after_stop` runs once
    the thread has ended.
    """

    thread_name = "netsim"

    def _init_thread(self) -> None:
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._error: BaseException | None = None
        #: outages added while it runs, shared by every direction (and connection)
        self.cuts = LinkCuts()

    def cut(self, seconds: float) -> tuple[int, int]:
        """Cut the link both ways for ``seconds`` from now (a pulled cable): what enters it
        meanwhile is lost (datagrams, messages) or waits for TCP's retransmissions (stream).
        Returns the cut's window on the monotonic clock, in ns."""
        t1 = time.monotonic_ns()
        t2 = t1 + round(seconds * 1e9)
        self.cuts.add(t1, t2)
        return t1, t2

    @property
    def is_running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    @property
    def error(self) -> BaseException | None:
        """The exception that ended the forwarding thread, if any."""
        return self._error

    @abstractmethod
    def start(self) -> None:
        """Open the sockets, then :meth:`_launch` the thread."""

    @abstractmethod
    def _run(self) -> None:
        """Forward until ``_stop`` is set; store an exception that ends it in ``_error``."""

    def _launch(self) -> None:
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=self.thread_name, daemon=True)
        self._thread.start()

    def _after_stop(self) -> None:  # noqa: B027 - an optional hook; nothing by default
        """What to release once the thread has ended (not if it hangs)."""

    def stop(self, timeout_s: float = 2.0) -> None:
        """Stop forwarding and close everything; what is still in flight is dropped."""
        thread, self._thread = self._thread, None
        if thread is None:
            return
        self._stop.set()
        thread.join(timeout_s)
        if thread.is_alive():  # only if a socket call hangs: leak rather than hang too
            log.error("%s thread did not stop within %.1f s", self.thread_name, timeout_s)
        else:
            self._after_stop()
        if self._error is not None:
            log.error("%s thread failed: %r", self.thread_name, self._error)

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


class LinkSimulator(ForwardingThread):
    """Forwards robot <-> operator traffic, each direction impaired by ``scenario``.

    Use as a context manager or call ``start()``/``stop()``. After
    ``start()``, ``operator_telemetry_endpoint`` and
    ``operator_commands_endpoint`` are the resolved bound addresses (bind to
    ``tcp://127.0.0.1:*`` in tests to get free ports).
    """

    def __init__(
        self,
        scenario: Scenario | None = None,
        *,
        endpoints: Endpoints | None = None,
        seed: int = 0,
        context: zmq.Context | None = None,
        hwm: int = 1000,
        spin_us: float = 300.0,
    ) -> None:
        self.scenario = scenario if scenario is not None else Scenario()
        self.endpoints = endpoints if endpoints is not None else Endpoints()
        self.seed = seed
        self.hwm = hwm
        #: Busy-wait this long before a due time instead of sleeping: a
        #: thread woken from sleep on a VM runs its first syscalls slowly
        #: (measured: released 260 us late at the median sleeping to the due
        #: time, 35 us spinning the last 300 us), at the cost of that much
        #: CPU per delayed release.
        if spin_us < 0:
            raise ConfigError(f"spin_us must be >= 0, not {spin_us}")
        self.spin_ns = round(spin_us * 1000)
        self._own_context = context is None
        self._ctx = context
        self._init_thread()
        self._dirs: list[_Direction] = []
        self.start_ns: int | None = None
        #: Per send: when it finished minus when it could have started
        #: (max of due time and receive time), the simulator's own cost.
        self._own_ns: deque[int] = deque(maxlen=100_000)
        self.operator_telemetry_endpoint: str | None = None
        self.operator_commands_endpoint: str | None = None

    # ------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Open the four sockets and start forwarding; raises ``LinkError`` on a bad endpoint."""
        if self._thread is not None:
            raise LinkError("LinkSimulator.start() called twice")
        if self._ctx is None:
            self._ctx = zmq.Context()
        ep = self.endpoints
        socks: list[zmq.Socket] = []
        try:
            from_robot = self._open(zmq.SUB, ep.robot_telemetry, bind=False, socks=socks)
            to_robot = self._open(zmq.PUB, ep.robot_commands, bind=False, socks=socks)
            to_operator = self._open(zmq.PUB, ep.operator_telemetry, bind=True, socks=socks)
            from_operator = self._open(zmq.SUB, ep.operator_commands, bind=True, socks=socks)
        except LinkError:
            for s in socks:
                s.close(0)
            self._close_context()
            raise
        self.operator_telemetry_endpoint = _last_endpoint(to_operator)
        self.operator_commands_endpoint = _last_endpoint(from_operator)
        self.start_ns = time.monotonic_ns()
        rx_tx = {"to_operator": (from_robot, to_operator), "to_robot": (from_operator, to_robot)}
        self._dirs = []
        for i, name in enumerate(DIRECTIONS):
            engine = DirectionImpairment(
                self.scenario.direction(name),
                seed=self.seed,
                name=name,
                start_ns=self.start_ns,
                cuts=self.cuts,
            )
            rx, tx = rx_tx[name]
            self._dirs.append(_Direction(name, rx, tx, engine))
            assert self._dirs[i].name == name
        self._launch()
        log.info(
            "netsim %r: robot %s / %s <-> operator %s / %s",
            self.scenario.name,
            ep.robot_telemetry,
            ep.robot_commands,
            self.operator_telemetry_endpoint,
            self.operator_commands_endpoint,
        )

    def _after_stop(self) -> None:
        self._close_context()

    # ------------------------------------------------------------ state
    def counters(self) -> dict[str, dict[str, Any]]:
        """A snapshot per direction name, with the impairments' counts by cause.

        Safe to call from any thread: the values are plain ints.
        """
        return {d.name: {**d.counters.as_dict(), **d.engine.counts.as_dict()} for d in self._dirs}

    def own_latency_ns(self) -> list[int]:
        """Recent per-send costs of the simulator itself, ns (at zero delay: receive to sent)."""
        return list(self._own_ns)

    # ------------------------------------------------------------ internals
    def _open(self, kind: int, endpoint: str, *, bind: bool, socks: list[zmq.Socket]) -> zmq.Socket:
        assert self._ctx is not None
        s = self._ctx.socket(kind)
        socks.append(s)
        s.setsockopt(zmq.LINGER, 0)
        s.setsockopt(zmq.SNDHWM if kind == zmq.PUB else zmq.RCVHWM, self.hwm)
        if kind == zmq.SUB:
            s.setsockopt(zmq.MAXMSGSIZE, _MAX_MESSAGE_BYTES)
            s.setsockopt(zmq.SUBSCRIBE, b"")
        try:
            if bind:
                s.bind(endpoint)
            else:
                s.connect(endpoint)
        except zmq.ZMQError as e:
            verb = "bind to" if bind else "connect to"
            raise LinkError(f"netsim cannot {verb} {endpoint}: {e}") from None
        return s

    def _close_context(self) -> None:
        if self._own_context and self._ctx is not None:
            self._ctx.destroy(linger=0)
            self._ctx = None

    def _run(self) -> None:
        set_timer_slack_ns(1_000)
        dirs = self._dirs
        fds = [d.fd for d in dirs]
        # select() has microsecond timeouts but only takes descriptors below
        # FD_SETSIZE; poll() takes any, to the millisecond (rounded up).
        use_select = max(fds) < 1024
        poller = select.poll()
        for fd in fds:
            poller.register(fd, select.POLLIN)
        heap: list[tuple[int, int, int, bytes, int]] = []
        own = self._own_ns
        spin_ns = self.spin_ns
        order = 0  # FIFO among equal due times
        now_ns = time.monotonic_ns
        stop = self._stop
        try:
            while not stop.is_set():
                # Read everything pending. The FDs are edge-triggered: a socket
                # is only known to be empty after EVENTS says so.
                pending = False  # a socket still holds messages: do not wait
                for i, d in enumerate(dirs):
                    rx, engine, c = d.rx, d.engine, d.counters
                    for _ in range(_MAX_BATCH):  # then release what is due
                        if not rx.getsockopt(zmq.EVENTS) & zmq.POLLIN:
                            break
                        data = rx.recv(zmq.NOBLOCK, copy=True)
                        t = now_ns()
                        c.received += 1
                        c.bytes_in += len(data)
                        out = engine.process(t, data)
                        if not out:
                            c.dropped += 1
                        elif len(out) > 1:
                            c.duplicated += len(out) - 1
                        for due, payload in out:
                            heapq.heappush(heap, (due, order, i, payload, t))
                            order += 1
                    else:
                        pending = True
                # Release everything due, in due order.
                t = now_ns()
                while heap and heap[0][0] <= t:
                    due, _, i, payload, t_recv = heapq.heappop(heap)
                    d = dirs[i]
                    d.tx.send(payload, zmq.NOBLOCK)
                    c = d.counters
                    c.sent += 1
                    c.bytes_out += len(payload)
                    late = t - due
                    if late > c.late_ns_max:
                        c.late_ns_max = late
                    t = now_ns()
                    own.append(t - (due if due > t_recv else t_recv))
                wait_s = _MAX_WAIT_S
                if heap:
                    wait_s = min(wait_s, (heap[0][0] - spin_ns - t) / 1e9)
                if wait_s > 0 and not pending:
                    if use_select:
                        select.select(fds, [], [], wait_s)
                    else:
                        poller.poll(math.ceil(wait_s * 1000))
        except BaseException as e:  # report, never die silently
            self._error = e
            log.exception("netsim forwarding stopped")
        finally:
            for d in dirs:
                d.rx.close(0)
                d.tx.close(0)


def _last_endpoint(sock: zmq.Socket) -> str:
    return sock.getsockopt(zmq.LAST_ENDPOINT).decode()
