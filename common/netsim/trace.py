"""Recorded links replayed: a one-way delay series, or Mahimahi delivery opportunities.

Two text formats, both looped when the run outlasts them:

- ``delays``: one ``t_s delay_ms`` pair a line (``#`` comments), times
  non-decreasing from the recording's start. A message entering the link
  at ``t`` gets the delay of the latest sample at or before ``t`` (a step
  function, so samples taken at a steady rate are replayed in the
  proportions they were recorded).
- ``mahimahi``: one integer millisecond a line, each an opportunity to
  deliver one 1500-byte packet (Mahimahi's ``mm-link`` trace format, as
  used by CellReplay). A message of ``n`` bytes waits for
  ``ceil(n / 1500)`` opportunities at or after it enters; opportunities
  nobody used are lost, as in ``mm-link``.

Either replaces the delay distribution (``delay_ms`` is still added, as
``mm-delay`` adds to ``mm-link``); loss and outages still apply on top.
"""

from __future__ import annotations

import bisect
import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from common.errors import ConfigError

TraceFormat = Literal["delays", "mahimahi"]
#: Bytes one Mahimahi delivery opportunity carries.
MAHIMAHI_PACKET_BYTES = 1500
NS_PER_MS = 1_000_000


@dataclass(frozen=True)
class DelayTrace:
    """A one-way delay series: ``times_ns[i]`` from the start, ``delays_ms[i]``."""

    times_ns: tuple[int, ...]
    delays_ms: tuple[float, ...]
    period_ns: int  # the trace loops after this

    def delay_ms(self, t_ns: int) -> float:
        """The recorded delay in effect ``t_ns`` after the start (looping)."""
        t = t_ns % self.period_ns if t_ns >= 0 else 0
        i = bisect.bisect_right(self.times_ns, t) - 1
        return self.delays_ms[max(i, 0)]


@dataclass(frozen=True)
class DeliveryTrace:
    """Mahimahi delivery opportunities, ms from the start, looping after the last."""

    opportunities_ms: tuple[int, ...]
    period_ms: int

    def opportunity_ns(self, k: int) -> int:
        """The time of the ``k``-th opportunity since the start (k counts across loops)."""
        n = len(self.opportunities_ms)
        loop, i = divmod(k, n)
        return (loop * self.period_ms + self.opportunities_ms[i]) * NS_PER_MS

    def first_at_or_after(self, t_ns: int) -> int:
        """Index (across loops) of the first opportunity at or after ``t_ns``."""
        n = len(self.opportunities_ms)
        period_ns = self.period_ms * NS_PER_MS
        loop, rest = divmod(max(t_ns, 0), period_ns)
        i = bisect.bisect_left(self.opportunities_ms, -(-rest // NS_PER_MS))
        return loop * n + i


def _lines(path: Path) -> list[list[str]]:
    try:
        text = path.read_text()
    except OSError as e:
        raise ConfigError(f"cannot read trace file {path}: {e}") from None
    out = []
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            out.append(line.split())
    if not out:
        raise ConfigError(f"trace file {path} holds no samples")
    return out


@functools.lru_cache(maxsize=16)
def load_delay_trace(path: str | Path) -> DelayTrace:
    """Parse a ``t_s delay_ms`` series; ``ConfigError`` names the bad line."""
    path = Path(path)
    times: list[int] = []
    delays: list[float] = []
    for n, fields in enumerate(_lines(path), 1):
        try:
            t_s, delay = float(fields[0]), float(fields[1])
        except (IndexError, ValueError):
            raise ConfigError(f"{path}: sample {n} is not 't_s delay_ms': {fields}") from None
        if delay < 0 or t_s < 0 or (times and round(t_s * 1e9) < times[-1]):
            raise ConfigError(f"{path}: sample {n} goes back in time or has a negative delay")
        times.append(round(t_s * 1e9))
        delays.append(delay)
    # Loop one mean interval after the last sample, so every sample lasts about as long.
    step = (times[-1] - times[0]) // max(1, len(times) - 1) if len(times) > 1 else NS_PER_MS
    return DelayTrace(
        tuple(t - times[0] for t in times), tuple(delays), times[-1] - times[0] + step
    )


@functools.lru_cache(maxsize=16)
def load_delivery_trace(path: str | Path) -> DeliveryTrace:
    """Parse Mahimahi's one-millisecond-a-line format."""
    path = Path(path)
    ms: list[int] = []
    for n, fields in enumerate(_lines(path), 1):
        try:
            value = int(fields[0])
        except ValueError:
            raise ConfigError(f"{path}: line {n} is not an integer millisecond") from None
        if value < 0 or (ms and value < ms[-1]):
            raise ConfigError(f"{path}: line {n} goes back in time")
        ms.append(value)
    if ms[-1] <= 0:
        raise ConfigError(f"{path}: the trace must end after 0 ms")
    return DeliveryTrace(tuple(ms), ms[-1])


def delay_percentiles_ms(trace: DelayTrace, quantiles: tuple[float, ...]) -> dict[float, float]:
    """The recorded delays' percentiles (nearest rank), what a replay should reproduce."""
    values = sorted(trace.delays_ms)
    top = len(values) - 1
    return {q: values[min(top, max(0, round(q * top)))] for q in quantiles}
