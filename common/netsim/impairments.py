"""What happens to each message on one direction of the link.

Pure and seeded: ``DirectionImpairment.process`` takes a message and the
time it entered the link and returns when (and as what bytes) it leaves.
No sockets and no clock reads, so the statistics are tested in virtual time
and the proxy only schedules what this module decides. The configuration
is ``link_config``'s, the random processes ``random_processes``'.

Determinism. Every random decision has its own generator, seeded from
(seed, direction, purpose), and each message consumes a fixed number of
draws from each: the n-th message meets the same fate for the same seed
whatever happened to the others, and changing one impairment (say, the
loss rate) leaves the delay sequence untouched. Outages, the rate queue and
head-of-line blocking depend on arrival times, which a real socket run
cannot fix; in virtual time they too repeat exactly.

The netem vocabulary is kept (percent + correlation, ``gemodel``, the
``pareto``/``paretonormal`` tables), with two deliberate departures:

- correlation is applied to a Gaussian copula (an AR(1) process in normal
  space mapped through the distribution's quantile function), so the
  configured distribution is what comes out at any correlation. netem mixes
  uniform variates instead, which narrows the distribution as correlation
  grows.
- correlated Bernoulli events (loss, duplication, ...) are a two-state
  Markov chain whose stationary rate is exactly the configured percent and
  whose lag-1 autocorrelation is the configured correlation.
"""

from __future__ import annotations

import bisect
import random
from collections import deque
from dataclasses import dataclass
from pathlib import Path

from common.netsim.link_config import (
    DIRECTIONS,
    MAX_RETRANSMISSIONS,
    NS_PER_MS,
    TOPIC_LEN,
    CorruptMode,
    Delivery,
    DirectionConfig,
    Distribution,
    LossModel,
    Mode,
    Scenario,
    unit_quantile,
)
from common.netsim.random_processes import CorrelatedBernoulli, CorrelatedDelay, GilbertElliott
from common.netsim.trace import (
    MAHIMAHI_PACKET_BYTES,
    DelayTrace,
    DeliveryTrace,
    load_delay_trace,
    load_delivery_trace,
)

#: the configuration's names, where the link simulator's users have always found them
__all__ = [
    "DIRECTIONS",
    "MAX_RETRANSMISSIONS",
    "NS_PER_MS",
    "TOPIC_LEN",
    "CorrelatedBernoulli",
    "CorrelatedDelay",
    "CorruptMode",
    "Delivery",
    "DirectionConfig",
    "DirectionImpairment",
    "Distribution",
    "GilbertElliott",
    "ImpairmentCounts",
    "LossModel",
    "Mode",
    "Scenario",
    "unit_quantile",
]


# ---------------------------------------------------------------- the engine
@dataclass
class ImpairmentCounts:
    """What the engine did, by cause (a message can count in several)."""

    lost: int = 0  # dropped by the loss model (datagram)
    outage_dropped: int = 0  # dropped because the link was down (datagram)
    queue_dropped: int = 0  # tail-dropped at the bottleneck queue
    gave_up: int = 0  # stream: still lost after MAX_RETRANSMISSIONS
    retransmitted: int = 0  # stream: messages that needed at least one retransmission
    held_back: int = 0  # delivered later than their own delay to keep order (stream, FIFO datagram)
    duplicated: int = 0
    reordered: int = 0
    corrupted: int = 0

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


class LinkCuts:
    """Outages added while a simulator runs (``deepxpalm netsim``'s SIGUSR1: a pulled cable),
    shared by every direction and connection of one simulator. Written by one thread, read by
    the forwarding threads: the windows are one tuple, replaced whole."""

    def __init__(self) -> None:
        self._windows: tuple[tuple[int, int], ...] = ()

    def add(self, t1_ns: int, t2_ns: int) -> None:
        self._windows = (*self._windows, (t1_ns, t2_ns))

    def down(self, t_ns: int) -> bool:
        return any(t1 <= t_ns < t2 for t1, t2 in self._windows)

    def __bool__(self) -> bool:
        return bool(self._windows)


class DirectionImpairment:
    """The impairment state machine of one direction.

    ``start_ns`` anchors the outage schedule; times are any monotonic
    nanosecond clock (real or virtual) as long as ``process`` is called with
    non-decreasing ``now_ns``. ``cuts``: outages added while it runs.
    """

    def __init__(
        self,
        config: DirectionConfig,
        *,
        seed: int = 0,
        name: str = "link",
        start_ns: int = 0,
        cuts: LinkCuts | None = None,
    ) -> None:
        self.config = config
        self._cuts = cuts if cuts is not None else LinkCuts()
        self.name = name
        self.seed = seed
        self.start_ns = start_ns
        self.counts = ImpairmentCounts()
        c = config

        def rng(purpose: str) -> random.Random:
            return random.Random(f"netsim:{seed}:{name}:{purpose}")

        self._delay = CorrelatedDelay(c, rng("delay"))
        self._dup_delay = CorrelatedDelay(c, rng("duplicate-delay"))
        if c.loss_model == "gilbert_elliott":
            self._loss: CorrelatedBernoulli | GilbertElliott = GilbertElliott(c, rng("loss"))
        else:
            self._loss = CorrelatedBernoulli(c.loss_percent, c.loss_correlation, rng("loss"))
        self._dup = CorrelatedBernoulli(c.duplicate_percent, c.duplicate_correlation, rng("dup"))
        self._reorder = CorrelatedBernoulli(c.reorder_percent, c.reorder_correlation, rng("ro"))
        self._corrupt = CorrelatedBernoulli(c.corrupt_percent, c.corrupt_correlation, rng("cor"))
        self._corrupt_at = rng("corrupt-position")
        self._corrupting = c.corrupt_percent > 0
        self._duplicating = c.duplicate_percent > 0
        self._retx = rng("retransmission")
        self._retx_loss = c.loss_rate()
        self._stream = c.delivery == "stream"
        self._retransmit_ns = round(c.retransmit_ms * NS_PER_MS)
        self._outages = sorted(
            (start_ns + round(t1 * 1e9), start_ns + round(t2 * 1e9)) for t1, t2 in c.outages
        )
        self._outage_starts = [o[0] for o in self._outages]
        self._ns_per_byte = 8e9 / (c.rate_kbit * 1000.0) if c.rate_kbit > 0 else 0.0
        self._queue: deque[int] = deque()  # finish times of messages at the bottleneck
        self._link_free_ns = 0
        self._last_due_ns = 0
        self._delay_trace: DelayTrace | None = None
        self._deliveries: DeliveryTrace | None = None
        self._next_opportunity = 0
        if c.trace_file:
            if c.trace_format == "mahimahi":
                self._deliveries = load_delivery_trace(Path(c.trace_file))
            else:
                self._delay_trace = load_delay_trace(Path(c.trace_file))

    def in_outage(self, t_ns: int) -> bool:
        """Whether the link is down at ``t_ns``: a scheduled outage, or a cut."""
        i = bisect.bisect_right(self._outage_starts, t_ns) - 1
        return (i >= 0 and t_ns < self._outages[i][1]) or self._cuts.down(t_ns)

    def process(self, now_ns: int, payload: bytes) -> list[tuple[int, bytes]]:
        """Deliveries ``(due_ns, bytes)`` for a message entering the link at ``now_ns``.

        An empty list is a drop; two entries a duplicate. Due times may be
        earlier than other messages' (datagram reordering) but never
        earlier than ``now_ns``.
        """
        c, counts = self.config, self.counts
        # Fixed draws per message from each enabled process, whatever the
        # message's fate, to keep runs aligned.
        lost = self._loss.step()
        dup = self._dup.step()
        reorder = self._reorder.step()
        corrupt = self._corrupt.step()
        u_corrupt = self._corrupt_at.random() if self._corrupting else 0.0
        delay_ms = self._delay.step()
        dup_delay_ms = self._dup_delay.independent() if self._duplicating else 0.0

        if self._delay_trace is not None:
            delay_ms = c.delay_ms + self._delay_trace.delay_ms(now_ns - self.start_ns)
        down = self.in_outage(now_ns) if self._outages or self._cuts else False
        if not self._stream and (lost or down):
            if down:
                counts.outage_dropped += 1
            else:
                counts.lost += 1
            return []

        # Bottleneck: serialise after whatever is queued; a full queue drops.
        t = now_ns
        if self._deliveries is not None:
            # Wait for enough delivery opportunities; unused ones are gone.
            trace, start = self._deliveries, self.start_ns
            k = max(self._next_opportunity, trace.first_at_or_after(now_ns - start))
            k += max(1, -(-(len(payload) + c.packet_overhead_bytes) // MAHIMAHI_PACKET_BYTES)) - 1
            t = start + trace.opportunity_ns(k)
            self._next_opportunity = k + 1
        elif self._ns_per_byte:
            q = self._queue
            while q and q[0] <= now_ns:
                q.popleft()
            if len(q) >= c.queue_limit:
                counts.queue_dropped += 1
                return []
            start = max(now_ns, self._link_free_ns)
            t = start + round((len(payload) + c.packet_overhead_bytes) * self._ns_per_byte)
            self._link_free_ns = t
            q.append(t)

        if self._stream and (lost or down):
            t = self._retransmit(t, lost, down)
            if t is None:
                counts.gave_up += 1
                return []

        if corrupt:
            payload = _corrupt(payload, u_corrupt, c.corrupt_mode)
            counts.corrupted += 1

        if reorder and not self._stream:
            counts.reordered += 1
            due = t
        else:
            due = t + round(delay_ms * NS_PER_MS)
        if self._stream or not (c.jitter_reorders or reorder):
            if due < self._last_due_ns:
                due = self._last_due_ns
                counts.held_back += 1
            self._last_due_ns = due
        out = [(due, payload)]
        if dup and not self._stream:
            counts.duplicated += 1
            out.append((t + round(dup_delay_ms * NS_PER_MS), payload))
        return out

    def _retransmit(self, t: int, lost: bool, down: bool) -> int | None:
        """When a message first lost at ``t`` finally gets through (stream model)."""
        self.counts.retransmitted += 1
        rto = self._retransmit_ns
        for _ in range(MAX_RETRANSMISSIONS):
            t += rto
            if (self._outages or self._cuts) and self.in_outage(t):
                rto *= 2  # no ACK comes back: TCP's timer backs off
                continue
            if self._retx.random() < self._retx_loss:
                # The connection is otherwise healthy, so ACKs for what
                # follows reveal the loss again after about the same time
                # (RACK), without backing off.
                rto = self._retransmit_ns
                continue
            return t
        return None


def _corrupt(payload: bytes, u: float, mode: str) -> bytes:
    """Damage ``payload`` so a validating decoder notices (truncate) or may not (bitflip).

    Truncation keeps the topic, so the subscriber's prefix filter still
    passes the message to its decoder, and removes at least one byte of the
    msgpack body. msgpack is self-delimiting: a strict prefix of one object
    is never a complete object, so ``unpackb`` always raises on it.
    """
    n = len(payload)
    if n <= TOPIC_LEN:
        return payload[: max(0, n - 1)]
    body = n - TOPIC_LEN
    if mode == "truncate":
        return payload[: TOPIC_LEN + min(int(u * body), body - 1)]
    bit = min(int(u * body * 8), body * 8 - 1)
    damaged = bytearray(payload)
    damaged[TOPIC_LEN + bit // 8] ^= 1 << (bit % 8)
    return bytes(damaged)
