"""What happens to each message on one direction of the link.

Pure and seeded: ``DirectionImpairment.process`` takes a message and the
time it entered the link and returns when (and as what bytes) it leaves.
No sockets and no clock reads, so the statistics are tested in virtual time
and the proxy only schedules what this module decides.

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
import dataclasses
import math
import random
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from statistics import NormalDist
from typing import Literal

from common.config import param
from common.errors import ConfigError
from common.netsim.trace import (
    MAHIMAHI_PACKET_BYTES,
    DelayTrace,
    DeliveryTrace,
    TraceFormat,
    load_delay_trace,
    load_delivery_trace,
)

NS_PER_MS = 1_000_000

#: Direction names: telemetry flows robot -> operator, commands the other way.
DIRECTIONS: tuple[str, str] = ("to_operator", "to_robot")

#: Bytes of a message that are its topic; corruption by truncation keeps
#: them so the damaged message still reaches the subscriber's decoder.
TOPIC_LEN = 4

#: A message still undelivered after this many retransmissions is given up
#: on (TCP would reset the connection and ZeroMQ reconnect, losing it).
MAX_RETRANSMISSIONS = 15

Distribution = Literal["uniform", "normal", "pareto", "paretonormal", "table"]
Delivery = Literal["stream", "datagram"]
Mode = Literal["stream", "message"]
LossModel = Literal["random", "gilbert_elliott"]
CorruptMode = Literal["truncate", "bitflip"]

_NORMAL = NormalDist()
_SQRT2 = math.sqrt(2.0)


# ---------------------------------------------------------------- distributions
def _pareto_q(u: float) -> float:
    """netem's ``pareto`` table as a quantile function.

    Pareto with shape 3 and scale 1 (mean 1.5), shifted to zero mean,
    scaled by 4/3 and clipped at 4 jitter units, as iproute2's table
    generator builds it; the delay is ``delay + jitter * q(u)``.
    """
    if u >= 1.0:
        return 4.0
    return min(4.0, (4.0 / 3.0) * ((1.0 - u) ** (-1.0 / 3.0) - 1.5))


def _normal_q(u: float) -> float:
    u = min(max(u, 1e-12), 1.0 - 1e-12)
    return _NORMAL.inv_cdf(u)


def _table_q(table: list[float], u: float) -> float:
    """Linear interpolation between order statistics of an empirical sample."""
    n = len(table)
    if n == 1:
        return table[0]
    x = u * (n - 1)
    i = min(int(x), n - 2)
    f = x - i
    return table[i] + f * (table[i + 1] - table[i])


def unit_quantile(distribution: str, u: float) -> float:
    """The standardised netem variate at probability ``u`` (jitter units)."""
    if distribution == "uniform":
        return 2.0 * u - 1.0
    if distribution == "normal":
        return _normal_q(u)
    if distribution == "pareto":
        return _pareto_q(u)
    if distribution == "paretonormal":
        # netem's paretonormal table: a quarter normal, three quarters
        # pareto, taken at the same probability (a comonotonic blend).
        return 0.25 * _normal_q(u) + 0.75 * _pareto_q(u)
    raise ConfigError(f"unknown delay distribution {distribution!r}")


# ---------------------------------------------------------------- config
@dataclass
class DirectionConfig:
    """Impairments of one direction, in netem's terms where netem has them."""

    delivery: Delivery = param(
        "stream",
        "stream: as ZeroMQ over TCP, nothing lost, a loss costs a retransmission and holds "
        "back what follows; datagram: losses are losses",
    )
    delay_ms: float = param(0.0, "base one-way delay (netem delay TIME)")
    jitter_ms: float = param(0.0, "spread around delay_ms, in the distribution's units")
    distribution: Distribution = param(
        "uniform", "uniform (netem's default), normal, pareto, paretonormal, or table"
    )
    delay_table_ms: list[float] = param(
        [], "distribution = table: measured extra delays, ms, added to delay_ms"
    )
    delay_correlation: float = param(0.0, "0..1, how much each delay follows the previous one")
    loss_model: LossModel = param("random", "random (percent + correlation) or gilbert_elliott")
    loss_percent: float = param(0.0, "random model: share of messages lost")
    loss_correlation: float = param(0.0, "random model: 0..1, lag-1 correlation of losses")
    ge_p_percent: float = param(1.0, "gilbert_elliott: chance per message of good -> bad")
    ge_r_percent: float = param(30.0, "gilbert_elliott: chance per message of bad -> good")
    ge_loss_bad_percent: float = param(100.0, "gilbert_elliott: loss in the bad state (1-h)")
    ge_loss_good_percent: float = param(0.0, "gilbert_elliott: loss in the good state (1-k)")
    duplicate_percent: float = param(0.0, "datagram only: share of messages delivered twice")
    duplicate_correlation: float = param(0.0, "0..1")
    reorder_percent: float = param(
        0.0, "datagram only: share sent at once, skipping delay_ms (netem reorder)"
    )
    reorder_correlation: float = param(0.0, "0..1")
    jitter_reorders: bool = param(
        True,
        "datagram: a packet drawn a shorter delay than the one before it overtakes it, as on "
        "a real path; false: jitter never reorders (netem with a FIFO queue behind it)",
    )
    corrupt_percent: float = param(0.0, "share of messages damaged so the decoder must reject them")
    corrupt_correlation: float = param(0.0, "0..1")
    corrupt_mode: CorruptMode = param(
        "truncate",
        "truncate: cut the msgpack body short, always rejected; bitflip: one random bit, "
        "realistic but may still decode",
    )
    rate_kbit: float = param(0.0, "bottleneck rate in kbit/s; 0 = unlimited")
    packet_overhead_bytes: int = param(0, "added to each message's size for the rate")
    queue_limit: int = param(1000, "messages waiting for the bottleneck; more are tail-dropped")
    retransmit_ms: float = param(
        200.0, "stream: delay a lost message costs until resent (doubles while the link is down)"
    )
    outages: list[tuple[float, float]] = param(
        [], "[[t1_s, t2_s], ...]: link down from t1 to t2 seconds after start"
    )
    trace_file: str = param(
        "", "a recorded link to replay instead of the delay distribution (relative to the file)"
    )
    trace_format: TraceFormat = param(
        "delays", "delays: 't_s delay_ms' lines; mahimahi: one delivery opportunity (ms) a line"
    )

    def __post_init__(self) -> None:
        for name in (
            "loss_percent",
            "ge_p_percent",
            "ge_r_percent",
            "ge_loss_bad_percent",
            "ge_loss_good_percent",
            "duplicate_percent",
            "reorder_percent",
            "corrupt_percent",
        ):
            v = getattr(self, name)
            if not 0.0 <= v <= 100.0:
                raise ConfigError(f"{name} must be within 0..100, not {v}")
        for name in (
            "delay_correlation",
            "loss_correlation",
            "duplicate_correlation",
            "reorder_correlation",
            "corrupt_correlation",
        ):
            v = getattr(self, name)
            if not 0.0 <= v < 1.0:
                raise ConfigError(f"{name} must be within 0..1 (1 excluded), not {v}")
        for name in ("delay_ms", "jitter_ms", "rate_kbit"):
            if getattr(self, name) < 0:
                raise ConfigError(f"{name} must be >= 0, not {getattr(self, name)}")
        if self.retransmit_ms <= 0:
            raise ConfigError(f"retransmit_ms must be > 0, not {self.retransmit_ms}")
        if self.queue_limit < 1:
            raise ConfigError(f"queue_limit must be >= 1, not {self.queue_limit}")
        if self.packet_overhead_bytes < 0:
            raise ConfigError("packet_overhead_bytes must be >= 0")
        if self.distribution == "table":
            if not self.delay_table_ms:
                raise ConfigError("distribution = 'table' needs a non-empty delay_table_ms")
            if min(self.delay_table_ms) < 0:
                raise ConfigError("delay_table_ms values must be >= 0")
        if self.loss_model == "gilbert_elliott" and self.ge_r_percent <= 0:
            raise ConfigError("ge_r_percent must be > 0, or the bad state never ends")
        if self.delivery == "stream":
            for name in ("duplicate_percent", "reorder_percent"):
                if getattr(self, name) > 0:
                    raise ConfigError(
                        f"{name} has no effect with delivery = 'stream': TCP delivers every "
                        "byte once and in order; use delivery = 'datagram'"
                    )
        for i, outage in enumerate(self.outages):
            if len(outage) != 2 or not 0 <= outage[0] < outage[1]:
                raise ConfigError(f"outages[{i}] must be [t1_s, t2_s] with 0 <= t1 < t2")

    # -------------------------------------------------------- what it means
    def delay_quantile_ms(self, u: float) -> float:
        """The configured one-way delay at probability ``u`` (before queueing and blocking).

        A ``delays`` trace is its recorded delays' quantile; a ``mahimahi``
        trace's delay depends on the traffic, so only ``delay_ms`` is known.
        """
        if self.trace_file:
            if self.trace_format == "mahimahi":
                return self.delay_ms
            values = sorted(load_delay_trace(Path(self.trace_file)).delays_ms)
            return self.delay_ms + _table_q(values, u)
        if self.distribution == "table":
            extra = _table_q(sorted(self.delay_table_ms), u)
            return self.delay_ms + extra
        return max(0.0, self.delay_ms + self.jitter_ms * unit_quantile(self.distribution, u))

    def loss_rate(self) -> float:
        """Stationary share of messages the loss model drops (outages excluded)."""
        if self.loss_model == "random":
            return self.loss_percent / 100.0
        p, r = self.ge_p_percent / 100.0, self.ge_r_percent / 100.0
        pi_bad = p / (p + r) if p + r > 0 else 0.0
        return pi_bad * self.ge_loss_bad_percent / 100.0 + (1 - pi_bad) * (
            self.ge_loss_good_percent / 100.0
        )

    def mean_loss_burst(self) -> float:
        """Expected length of a run of consecutive losses (outages excluded)."""
        if self.loss_model == "random":
            p, rho = self.loss_percent / 100.0, self.loss_correlation
            stay = p + rho * (1.0 - p)
            return 1.0 / (1.0 - stay) if p > 0 else 0.0
        # Hidden Markov: bursts = P(loss at n, no loss at n+1); length = rate / that.
        p, r = self.ge_p_percent / 100.0, self.ge_r_percent / 100.0
        lb, lg = self.ge_loss_bad_percent / 100.0, self.ge_loss_good_percent / 100.0
        pi_b = p / (p + r) if p + r > 0 else 0.0
        pi_g = 1.0 - pi_b
        # P(next not lost | now good/bad), transitions happen before each message.
        ng = (1 - p) * (1 - lg) + p * (1 - lb)
        nb = r * (1 - lg) + (1 - r) * (1 - lb)
        ends = pi_g * lg * ng + pi_b * lb * nb
        rate = pi_g * lg + pi_b * lb
        return rate / ends if ends > 0 else 0.0


@dataclass
class Scenario:
    """A named link: one impairment config per direction."""

    name: str = param("none", "shown in logs and reports")
    description: str = param("no impairment", "one line on what the link stands for")
    mode: Mode = param(
        "stream",
        "stream: forward TCP bytes unchanged (CURVE passes); message: re-publish ZeroMQ "
        "messages (per-message loss, duplication, reordering, corruption; no CURVE)",
    )
    to_operator: DirectionConfig = param(DirectionConfig(), "robot -> operator (telemetry)")
    to_robot: DirectionConfig = param(DirectionConfig(), "operator -> robot (commands)")

    def direction(self, name: str) -> DirectionConfig:
        if name not in DIRECTIONS:
            raise ConfigError(f"unknown direction {name!r}; known: {list(DIRECTIONS)}")
        return getattr(self, name)

    def with_delay(self, name: str, delay_ms: float) -> Scenario:
        """A copy with one direction's base delay replaced (CLI overrides)."""
        d = dataclasses.replace(self.direction(name), delay_ms=delay_ms)
        return dataclasses.replace(self, **{name: d})


# ---------------------------------------------------------------- random processes
class CorrelatedBernoulli:
    """Events at rate ``p`` whose lag-1 autocorrelation is ``rho``; one draw per step.

    At rate 0 nothing is drawn: the generator is this process's own, so
    skipping it changes no other decision, and a disabled impairment costs
    nothing per message.
    """

    __slots__ = ("_off", "_p_after_0", "_p_after_1", "_rng", "last")

    def __init__(self, percent: float, correlation: float, rng: random.Random) -> None:
        p = percent / 100.0
        self._off = p <= 0.0
        self._p_after_1 = p + correlation * (1.0 - p)
        self._p_after_0 = p * (1.0 - correlation)
        self._rng = rng
        self.last = False

    def step(self) -> bool:
        if self._off:
            return False
        u = self._rng.random()
        self.last = u < (self._p_after_1 if self.last else self._p_after_0)
        return self.last


class GilbertElliott:
    """Two-state burst loss (netem ``loss gemodel p r 1-h 1-k``); two draws per step."""

    __slots__ = ("_lb", "_lg", "_p", "_r", "_rng", "bad")

    def __init__(self, config: DirectionConfig, rng: random.Random) -> None:
        self._p = config.ge_p_percent / 100.0
        self._r = config.ge_r_percent / 100.0
        self._lb = config.ge_loss_bad_percent / 100.0
        self._lg = config.ge_loss_good_percent / 100.0
        self._rng = rng
        self.bad = False

    def step(self) -> bool:
        u_move, u_loss = self._rng.random(), self._rng.random()
        if self.bad:
            if u_move < self._r:
                self.bad = False
        elif u_move < self._p:
            self.bad = True
        return u_loss < (self._lb if self.bad else self._lg)


class CorrelatedDelay:
    """Delays with the configured marginal distribution and AR(1) dependence."""

    __slots__ = ("_a", "_b", "_base", "_dist", "_fixed", "_jitter", "_rng", "_table", "_z")

    def __init__(self, config: DirectionConfig, rng: random.Random) -> None:
        rho = config.delay_correlation
        self._a = rho
        self._b = math.sqrt(1.0 - rho * rho)
        self._base = config.delay_ms
        self._jitter = config.jitter_ms
        self._dist = config.distribution
        self._table = sorted(config.delay_table_ms)
        self._rng = rng
        self._z = rng.gauss(0.0, 1.0)  # start in the stationary distribution
        #: No spread: a constant needs no draws (see CorrelatedBernoulli).
        self._fixed = (
            config.delay_ms if config.distribution != "table" and not config.jitter_ms else None
        )

    def step(self) -> float:
        """The next delay in ms (never negative)."""
        if self._fixed is not None:
            return self._fixed
        self._z = self._a * self._z + self._b * self._rng.gauss(0.0, 1.0)
        return self._at(self._z)

    def independent(self) -> float:
        """A delay drawn afresh, for duplicates, without moving the chain."""
        if self._fixed is not None:
            return self._fixed
        return self._at(self._rng.gauss(0.0, 1.0))

    def _at(self, z: float) -> float:
        if self._dist == "normal":
            return max(0.0, self._base + self._jitter * z)
        u = 0.5 * (1.0 + math.erf(z / _SQRT2))
        if self._dist == "table":
            return self._base + _table_q(self._table, u)
        return max(0.0, self._base + self._jitter * unit_quantile(self._dist, u))


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


class DirectionImpairment:
    """The impairment state machine of one direction.

    ``start_ns`` anchors the outage schedule; times are any monotonic
    nanosecond clock (real or virtual) as long as ``process`` is called with
    non-decreasing ``now_ns``.
    """

    def __init__(
        self, config: DirectionConfig, *, seed: int = 0, name: str = "link", start_ns: int = 0
    ) -> None:
        self.config = config
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
        """Whether the link is down at ``t_ns``."""
        i = bisect.bisect_right(self._outage_starts, t_ns) - 1
        return i >= 0 and t_ns < self._outages[i][1]

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
        down = self.in_outage(now_ns) if self._outages else False
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
            if self._outages and self.in_outage(t):
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
