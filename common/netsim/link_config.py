"""A link's impairments as configured: one direction's (``DirectionConfig``), a scenario's two.

The netem vocabulary is kept (percent + correlation, ``gemodel``, the
``pareto``/``paretonormal`` tables); ``unit_quantile`` is each delay
distribution as a quantile function, in jitter units. What the
configuration means for each message is ``common.netsim.impairments``'.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from statistics import NormalDist
from typing import Literal

from common.config.typed import param
from common.errors import ConfigError
from common.netsim.trace import TraceFormat, load_delay_trace

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


def table_quantile(table: list[float], u: float) -> float:
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
            return self.delay_ms + table_quantile(values, u)
        if self.distribution == "table":
            extra = table_quantile(sorted(self.delay_table_ms), u)
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
