"""A node's link over the Zenoh fabric: the same ``Sender`` and ``Receiver`` as ZeroMQ's.

What travels is the codec's frame, byte for byte as on a direct link (topic,
robot name, msgpack, signature); the key expression (keyexprs.py) routes it.
Each kind of message gets the quality of service it needs:

- stimuli, display frames and heartbeats: best-effort, dropped under
  congestion, express; stimuli at the highest priority. Each is worth something
  only while it is the newest (a heartbeat confirms the current stimulus and
  the sender's liveness, and the next one says the same 50 ms later), so none
  waits behind a lost packet (QUIC datagrams);
- commands and video signals: reliable (a QUIC stream), dropped
  rather than queued when the session cannot send (the router is away): the
  node's own freshness rules see the silence;
- an operator's ``arm_stop``: reliable at the highest priority, and
  ``STOP_COPIES`` best-effort copies beside it under a key of their own
  (``stop_copy``: the router's rate gate passes the first of each key, so a
  copy never takes the reliable stop's turn), so a lost packet cannot delay
  it by a retransmission. The receiver keeps the first to arrive and drops the rest
  (``stop_copies_dropped``); the operator node also resends a stop until the
  robot's heartbeat shows it latched.

Receiving never blocks Zenoh: the callback only appends to a bounded queue (a
slot of one per latest-value key) and wakes the node's poll through a pipe.
Decoding, signature checks and everything else happen on the node's thread in
``drain``, exactly as for ``common.wire.transport.Subscriber``.
"""

from __future__ import annotations

import collections
import contextlib
import hashlib
import logging
import math
import os
import threading
from collections import Counter
from typing import Any

import zmq

from common.clocks.clock import now_ns
from common.fabric import keyexprs
from common.logs import BurstLog
from common.wire.codec import (
    DecodeError,
    WrongRobotError,
    decode_named,
    encode,
    name_prefix,
)
from common.wire.messages import Message, TactileFrame

log = logging.getLogger(__name__)

#: best-effort copies of an arm_stop sent beside its reliable one (the router passes the first
#: that reaches it; the second stands in for a first lost on the way)
STOP_COPIES = 2
#: the largest message that travels best-effort: one QUIC datagram holds it whole. Measured
#: through a lossy path: up to 1,100 bytes every message arrived; at 1,300 one in six was lost,
#: at 1,800 nearly half (a message split over datagrams is lost with any of them). A larger
#: latest-value message goes reliably instead (``link_fabric_too_big_for_a_datagram``)
DATAGRAM_BYTES = 1100
#: the least time between two of a robot's heartbeats on the fabric. The router lets one of
#: each key through per 1/hz (``router_side.acl.RateLimits.robot_heartbeat_hz``, 200/s: 5 ms)
#: and drops the newer; a heartbeat that announces a lease or latch change sent 2 ms after the
#: periodic one was dropped, and the change showed 50 ms later. Twice the gate's interval, so
#: that jitter that halves two heartbeats' spacing on the way still lets both through
HEARTBEAT_SPACING_MS = 10.0
#: how many stop payloads the receiver remembers per sender to drop the copies of: one
#: sender's flood of stops (at its key's gated rate) turns over its own memory, nobody else's
_STOP_MEMORY = 32
#: key expressions a subscriber keeps a queue for at most (one per sender and kind)
_MAX_QUEUES = 1024
#: the queue of messages taken but not yet decoded (``drain``'s limit), read first next time
_REST = ""


def _qos(kind: str, best_effort: bool) -> dict[str, Any]:
    import zenoh

    priority = {
        "stimulus": zenoh.Priority.REAL_TIME,
        keyexprs.STOP: zenoh.Priority.REAL_TIME,
        "command": zenoh.Priority.INTERACTIVE_HIGH,
        "heartbeat": zenoh.Priority.INTERACTIVE_LOW,
        "frame": zenoh.Priority.DATA_HIGH,
        "video": zenoh.Priority.DATA,
    }[kind]
    return {
        "reliability": zenoh.Reliability.BEST_EFFORT if best_effort else zenoh.Reliability.RELIABLE,
        # BLOCK could hold the node's loop on a congested link: nothing here waits
        "congestion_control": zenoh.CongestionControl.DROP,
        "express": True,
        "priority": priority,
    }


class FabricPublisher:
    """Sends a node's messages to their key expressions (``Sender``).

    ``robot``: the robot the messages are of (our own name on a robot).
    ``operator``: our roster name when we are an operator, None on a robot.
    """

    def __init__(
        self,
        session: Any,
        *,
        robot: bytes,
        operator: str | None,
        signer: Any = None,
        endpoint: str = "",
    ) -> None:
        self.session = session
        self.name = robot
        self.signer = signer
        self.from_robot = operator is None
        self.endpoint = endpoint
        self.sent = 0
        self.bytes_sent = 0
        self.send_errors = 0
        kinds = keyexprs.ROBOT_KINDS if self.from_robot else keyexprs.OPERATOR_KINDS
        names = set(kinds.values()) | (set() if self.from_robot else {keyexprs.STOP})
        self._pubs: dict[str, Any] = {}
        self._reliable: dict[str, Any] = {}  # latest-value kinds, for messages too big
        self._copies: Any = None
        self.too_big = 0
        for kind in sorted(names):
            key = (
                keyexprs.robot_key(robot, kind)
                if self.from_robot
                else keyexprs.operator_key(robot, operator, kind)
            )
            best_effort = kind in keyexprs.LATEST_VALUE_KINDS
            self._pubs[kind] = session.declare_publisher(key, **_qos(kind, best_effort))
            if best_effort:
                self._reliable[kind] = session.declare_publisher(key, **_qos(kind, False))
            if kind == keyexprs.STOP:  # the copy under its own key (keyexprs.STOP_COPY)
                copy_key = keyexprs.operator_key(robot, operator, keyexprs.STOP_COPY)
                self._copies = session.declare_publisher(copy_key, **_qos(kind, True))

    def send(self, msg: Message) -> bytes:
        data = encode(msg, self.name, self.signer)
        self.send_raw(data, keyexprs.kind_of(msg, self.from_robot))
        return data

    def send_raw(self, data: bytes, kind: str) -> None:
        import zenoh

        pub = self._pubs[kind]
        if len(data) > DATAGRAM_BYTES and kind in self._reliable:
            pub = self._reliable[kind]
            self.too_big += 1
        try:
            pub.put(data)
            if kind == keyexprs.STOP:
                for _ in range(STOP_COPIES):
                    self._copies.put(data)
        except zenoh.ZError as e:  # a closed session: the node is shutting down
            self.send_errors += 1
            log.debug("fabric put on %s failed: %s", kind, e)
            return
        self.sent += 1
        self.bytes_sent += len(data)

    def health(self) -> dict[str, float]:
        """``link_fabric_router_up`` (1/0): whether our session reaches its router now."""
        try:
            up = bool(list(self.session.info.routers_zid()))
        except Exception:  # a closed session
            up = False
        return {
            "link_fabric_router_up": float(up),
            "link_fabric_send_errors": float(self.send_errors),
            "link_fabric_too_big_for_a_datagram": float(self.too_big),
        }

    def read_subscriptions(self) -> bool:
        """Nothing to read: Zenoh tells each publisher whether anyone matches (``wanted``)."""
        return False

    def wanted(self, prefix: bytes) -> bool:
        """Does anyone read raw frames? (Only frames are skipped when nobody does.)"""
        if not self.from_robot or prefix != name_prefix(TactileFrame.TOPIC, self.name):
            return True
        try:
            return bool(self._pubs["frame"].matching_status.matching)
        except Exception:  # a closed session: sending is moot anyway
            return False

    def close(self) -> None:
        for pub in (*self._pubs.values(), *self._reliable.values(), self._copies):
            if pub is not None:
                with contextlib.suppress(Exception):
                    pub.undeclare()
        self._pubs.clear()
        self._reliable.clear()
        self._copies = None


class FabricSubscriber:
    """Receives a node's messages from key expressions (``Receiver``).

    Latest-value keys keep one message each (the newest); the others queue up
    to ``queue`` messages per key expression, so per sender, the oldest dropped
    first when that sender floods (``queue_dropped``). ``poller`` is a
    ``zmq.Poller`` on the wake pipe, so a node can register its other file
    descriptors beside it, as with ZeroMQ.
    """

    def __init__(
        self,
        session: Any,
        keys: tuple[str, ...],
        *,
        expect_name: bytes | None,
        name: str = "subscriber",
        queue: int = 256,
        endpoint: str = "",
        latest_value: bool = True,
    ) -> None:
        """``latest_value=False``: every message queued, latest-value kinds too (a recorder
        or a test that counts every message, not a node that acts on the newest)."""
        self.endpoint = endpoint
        self._latest_kinds = keyexprs.LATEST_VALUE_KINDS if latest_value else frozenset()
        self.expect_name = expect_name
        self.received = 0
        self.rejected: Counter[str] = Counter()
        self.counters: Counter[str] = Counter()
        self._bad = BurstLog(log, f"{name}: rejected message")
        #: one bounded queue per key expression, so per sender (the router lets a member put
        #: under its own name only): a flood from one key drops its own oldest, nobody else's
        self._queues: dict[str, collections.deque[tuple[int, bytes]]] = {}
        self._queue_max = queue
        self._queued = 0
        self._latest: dict[str, tuple[int, bytes]] = {}
        #: per sender (the key without its kind): the digests of its latest stops
        self._stops: dict[str, collections.deque[bytes]] = {}
        self._lock = threading.Lock()
        self._rfd, self._wfd = os.pipe2(os.O_NONBLOCK | os.O_CLOEXEC)
        self._woken = False
        self.sock = self._rfd  # what ``ready`` reports as readable when messages wait
        self.poller = zmq.Poller()
        self.poller.register(self._rfd, zmq.POLLIN)
        self._subs = [session.declare_subscriber(key, self._on_sample) for key in keys]

    # ------------------------------------------------------------ Zenoh's thread
    def _on_sample(self, sample: Any) -> None:
        t_recv = now_ns()
        key = str(sample.key_expr)
        data = sample.payload.to_bytes()
        kind = key.rsplit("/", 1)[-1]
        with self._lock:
            if kind in self._latest_kinds:
                if key in self._latest:
                    self.counters["superseded"] += 1
                self._latest[key] = (t_recv, data)
            else:
                if kind in keyexprs.STOP_KINDS and self._seen_stop(key, data):
                    self.counters["stop_copies_dropped"] += 1
                    return
                queue = self._queues.get(key)
                if queue is None:
                    if len(self._queues) >= _MAX_QUEUES:  # keys seen: bounded by the roster
                        self.counters["queue_dropped"] += 1
                        return
                    queue = self._queues[key] = collections.deque()
                if len(queue) >= self._queue_max:
                    queue.popleft()
                    self.counters["queue_dropped"] += 1
                    self._queued -= 1
                queue.append((t_recv, data))
                self._queued += 1
            if not self._woken:  # one byte in the pipe while anything waits, never more
                self._woken = True
                with contextlib.suppress(BlockingIOError, OSError):
                    os.write(self._wfd, b"!")

    def _seen_stop(self, key: str, data: bytes) -> bool:
        """Is ``data`` a stop its sender already sent (a copy)? Remembered if not."""
        sender = key.rsplit("/", 1)[0]
        seen = self._stops.get(sender)
        if seen is None:
            if len(self._stops) >= _MAX_QUEUES:  # senders: bounded by the roster
                del self._stops[next(iter(self._stops))]
            seen = self._stops[sender] = collections.deque(maxlen=_STOP_MEMORY)
        digest = hashlib.blake2b(data, digest_size=16).digest()
        if digest in seen:
            return True
        seen.append(digest)
        return False

    # -------------------------------------------------------------- node's thread
    def poll(self, timeout_s: float) -> bool:
        return bool(self.ready(timeout_s))

    def ready(self, timeout_s: float) -> dict[Any, int]:
        """Wait up to ``timeout_s``; what is readable (the wake pipe and anything beside it)."""
        return dict(self.poller.poll(math.ceil(max(0.0, timeout_s) * 1000)))

    def _take(self) -> list[tuple[int, bytes]]:
        # The pipe is emptied and the flag cleared under the lock the callback writes under:
        # a byte written after this belongs to a message this call does not take.
        with self._lock:
            if self._woken:
                with contextlib.suppress(BlockingIOError, OSError):
                    os.read(self._rfd, 64)
                self._woken = False
            items: list[tuple[int, bytes]] = []
            if self._queued:
                for queue in self._queues.values():
                    items.extend(queue)
                    queue.clear()
                self._queued = 0
            if self._latest:
                items.extend(self._latest.values())
                self._latest.clear()
            if len(items) > 1:
                items.sort(key=lambda item: item[0])
        return items

    def drain_raw(self) -> list[tuple[int, bytes]]:
        """Every waiting message as received, undecoded, with its receive time, oldest first
        (a recorder checks and counts them itself)."""
        return self._take()

    def drain(
        self, max_messages: int = 1024, wires: list[bytes] | None = None
    ) -> list[tuple[Message, int]]:
        """Every valid waiting message with its local receive time, oldest first.

        At most ``max_messages`` are decoded; the rest wait for the next call
        (the wake pipe is set again so the caller's poll sees them).
        """
        items = self._take()
        if len(items) > max_messages:
            rest = items[max_messages:]
            items = items[:max_messages]
            with self._lock:
                queue = self._queues.setdefault(_REST, collections.deque())
                queue.extendleft(reversed(rest))
                self._queued += len(rest)
                if not self._woken:
                    self._woken = True
                    with contextlib.suppress(BlockingIOError, OSError):
                        os.write(self._wfd, b"!")
        out: list[tuple[Message, int]] = []
        for t_recv, data in items:
            self.received += 1
            try:
                robot, msg = decode_named(data)
                if self.expect_name is not None and robot != self.expect_name:
                    raise WrongRobotError(f"for robot {robot!r}, not {self.expect_name!r}")
            except DecodeError as e:
                self.rejected[type(e).__name__] += 1
                self._bad(str(e))
                continue
            out.append((msg, t_recv))
            if wires is not None:
                wires.append(data)
        return out

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())

    def health(self) -> dict[str, float]:
        """What the receiving side dropped itself: older latest values, flood overflow, copies."""
        with self._lock:  # Zenoh's threads add keys to it
            counters = dict(self.counters)
        return {f"link_fabric_{k}": float(v) for k, v in counters.items()}

    def close(self) -> None:
        for sub in self._subs:
            with contextlib.suppress(Exception):
                sub.undeclare()
        self._subs.clear()
        with contextlib.suppress(OSError):
            os.close(self._rfd)
        with contextlib.suppress(OSError):
            os.close(self._wfd)
