"""A node's link as its callers see it (``Link``: a sender and a receiver), and one in memory.

A node opens its ZeroMQ link (``common.wire.transport``) in ``run()``; one handed
a link instead is driven by its caller: the bench, replay and tests, with
real sockets or a ``CaptureLink`` that keeps what the node sends and feeds
it what ``deliver`` queues.
"""

from __future__ import annotations

import collections
from collections import Counter
from dataclasses import dataclass
from typing import Protocol

from common.wire.codec import encode
from common.wire.messages import Message


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
