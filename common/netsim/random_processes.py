"""The seeded random processes behind the impairments: correlated events, burst loss, delays.

Correlation is applied to a Gaussian copula (an AR(1) process in normal
space mapped through the distribution's quantile function), so the
configured distribution is what comes out at any correlation; correlated
Bernoulli events are a two-state Markov chain whose stationary rate is the
configured percent and whose lag-1 autocorrelation the configured
correlation. Each process draws from its own generator.
"""

from __future__ import annotations

import math
import random

from common.netsim.link_config import DirectionConfig, table_quantile, unit_quantile

_SQRT2 = math.sqrt(2.0)


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
            return self._base + table_quantile(self._table, u)
        return max(0.0, self._base + self._jitter * unit_quantile(self._dist, u))
