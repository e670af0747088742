"""Rolling statistics of one message stream at its receiver: latency, jitter, loss, staleness.

One ``LinkStats`` per stream whose ``seq`` counts up by one per message
(per sender and message type, e.g. the robot's stimuli). Updates are O(1)
and allocate nothing beyond Python ints, so the operator's 60 Hz loop can
call ``on_message`` for every message; ``snapshot`` is for the live view
and the demo's JSON, a few times a second.

- Latency is one-way: the receive time minus the send time mapped onto
  our clock with the heartbeat clock offset (``common.clocks.clock_sync``). Its
  error is the offset's (see ``ClockEstimate.uncertainty_ns``). Until the
  offset is known, latency is left out rather than guessed.
- Jitter is RFC 3550's interarrival jitter: the smoothed absolute change in
  transit time between consecutive arrivals. It needs no clock offset.
- Loss comes from gaps in ``seq``. A message that arrives after a gap was
  counted (reordering) is taken back out of the loss count; one seen twice
  is a duplicate. Bursts are runs of consecutive missing ``seq``.
- Staleness is how long ago the newest message arrived, and how old the
  data it carries was at that moment plus since.

The window is a ring of time buckets (default 60 one-second buckets); a
bucket is cleared when its second comes round again, so counts cover the
last ``window_s`` without storing messages. Latency percentiles come from a
log-spaced histogram (bins 4% wide) kept for the whole window by adding
each message and subtracting a bucket's histogram when it expires.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

from common.clocks.clock_sync import ClockSync

_HIST_MIN_NS = 10_000  # 10 us: the first bin holds everything below
_HIST_RATIO = 1.04
_HIST_BINS = 400  # up to 10 us * 1.04**399, about 60 s
_LOG_RATIO = math.log(_HIST_RATIO)
_SEQ_WINDOW = 64  # how far back duplicates and late arrivals are recognised
_SEQ_MASK = (1 << _SEQ_WINDOW) - 1
#: a jump this large in a sender's seq is a restart, not messages lost
SEQ_RESTART_GAP = 100_000


@dataclass(frozen=True, slots=True)
class LinkSnapshot:
    """The statistics of the last ``window_s`` seconds (JSON-able via ``as_dict``)."""

    window_s: float
    received: int
    lost: int
    loss_rate: float  # lost / (received + lost)
    duplicates: int
    reordered: int  # arrived after a later seq
    loss_bursts: int
    max_loss_burst: int
    mean_loss_burst: float
    latency_mean_ms: float | None  # None until the clock offset is known
    latency_p50_ms: float | None
    latency_p99_ms: float | None
    latency_max_ms: float | None
    jitter_ms: float  # RFC 3550, smoothed over about 16 arrivals
    since_last_ms: float | None  # time since the newest message arrived
    newest_age_ms: float | None  # age of the newest message's data now
    clock_offset_ms: float | None
    clock_uncertainty_ms: float | None

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def _bin(latency_ns: int) -> int:
    if latency_ns <= _HIST_MIN_NS:
        return 0
    i = int(math.log(latency_ns / _HIST_MIN_NS) / _LOG_RATIO) + 1
    return i if i < _HIST_BINS else _HIST_BINS - 1


def _bin_value_ns(i: int) -> float:
    """A bin's geometric centre."""
    if i == 0:
        return _HIST_MIN_NS
    return _HIST_MIN_NS * _HIST_RATIO ** (i - 0.5)


class LinkStats:
    """Receiver-side statistics of one stream over a sliding time window."""

    def __init__(
        self,
        *,
        clock: ClockSync | None = None,
        same_clock: bool = False,
        window_s: float = 60.0,
        bucket_s: float = 1.0,
    ) -> None:
        if not 0 < bucket_s <= window_s:
            raise ValueError(f"need 0 < bucket_s <= window_s, not {bucket_s} and {window_s}")
        self.clock = clock
        #: Sender and receiver read the same clock (one machine): offset 0.
        self.same_clock = same_clock
        self.window_s = window_s
        self._bucket_ns = round(bucket_s * 1e9)
        n = math.ceil(window_s / bucket_s)
        self._n = n
        self._epoch = [-1] * n
        self._received = [0] * n
        self._lost = [0] * n
        self._dup = [0] * n
        self._reordered = [0] * n
        self._bursts = [0] * n
        self._burst_sum = [0] * n
        self._burst_max = [0] * n
        self._lat_n = [0] * n
        self._lat_sum = [0] * n
        self._lat_max = [0] * n
        self._hist = [[0] * _HIST_BINS for _ in range(n)]
        self._window_hist = [0] * _HIST_BINS
        self._highest: int | None = None
        self._seen = 0  # bit k: highest - k has arrived
        self._last_transit: int | None = None
        self._jitter_ns = 0.0
        self._last_recv_ns: int | None = None
        self._newest_send_ns: int | None = None

    # ------------------------------------------------------------ updates
    def _slot(self, t_ns: int) -> int:
        b = t_ns // self._bucket_ns
        s = b % self._n
        if self._epoch[s] != b:
            self._clear(s)
            self._epoch[s] = b
        return s

    def _clear(self, s: int) -> None:
        h, wh = self._hist[s], self._window_hist
        if self._lat_n[s]:
            for i, c in enumerate(h):
                if c:
                    wh[i] -= c
                    h[i] = 0
        self._received[s] = self._lost[s] = self._dup[s] = self._reordered[s] = 0
        self._bursts[s] = self._burst_sum[s] = self._burst_max[s] = 0
        self._lat_n[s] = self._lat_sum[s] = self._lat_max[s] = 0

    def _offset_ns(self) -> int | None:
        if self.clock is not None:
            return self.clock.offset_ns
        return 0 if self.same_clock else None

    def on_message(self, seq: int, t_send_ns: int, t_recv_ns: int) -> None:
        """Count one arrival: its ``seq``, the sender's ``t_send_ns``, our ``t_recv_ns``."""
        s = self._slot(t_recv_ns)
        hi = self._highest
        if hi is None or seq - hi > SEQ_RESTART_GAP or hi - seq > SEQ_RESTART_GAP:
            self._highest, self._seen = seq, 1  # first message, or the sender restarted
        elif seq > hi:
            gap = seq - hi - 1
            if gap:
                self._lost[s] += gap
                self._bursts[s] += 1
                self._burst_sum[s] += gap
                if gap > self._burst_max[s]:
                    self._burst_max[s] = gap
            self._seen = ((self._seen << (seq - hi)) | 1) & _SEQ_MASK
            self._highest = seq
        else:
            k = hi - seq
            if k < _SEQ_WINDOW and self._seen >> k & 1:
                self._dup[s] += 1
                return
            if k < _SEQ_WINDOW:
                self._seen |= 1 << k
            self._reordered[s] += 1
            self._lost[s] -= 1  # it was counted lost when the gap opened
        self._received[s] += 1
        self._last_recv_ns = t_recv_ns
        if self._newest_send_ns is None or seq == self._highest:
            self._newest_send_ns = t_send_ns

        transit = t_recv_ns - t_send_ns  # includes the clock offset, which cancels
        if self._last_transit is not None:
            d = abs(transit - self._last_transit)
            self._jitter_ns += (d - self._jitter_ns) / 16.0
        self._last_transit = transit

        offset = self._offset_ns()
        if offset is not None:
            latency = t_recv_ns - (t_send_ns - offset)
            self._lat_n[s] += 1
            self._lat_sum[s] += latency
            if latency > self._lat_max[s]:
                self._lat_max[s] = latency
            i = _bin(latency)
            self._hist[s][i] += 1
            self._window_hist[i] += 1

    # ------------------------------------------------------------ queries
    def snapshot(self, now_ns: int) -> LinkSnapshot:
        """Statistics over the last ``window_s`` as of ``now_ns`` (our clock)."""
        self._slot(now_ns)  # expire what is due even if nothing arrived lately
        b_now = now_ns // self._bucket_ns
        live = []
        for s in range(self._n):
            if b_now - self._epoch[s] < self._n:
                live.append(s)
            elif self._epoch[s] >= 0:  # older than the window: forget it
                self._clear(s)
                self._epoch[s] = -1
        received = sum(self._received[s] for s in live)
        lost = max(0, sum(self._lost[s] for s in live))
        bursts = sum(self._bursts[s] for s in live)
        lat_n = sum(self._lat_n[s] for s in live)
        offset = self._offset_ns()
        est = self.clock.estimate(now_ns) if self.clock is not None else None
        p50 = p99 = mean = lat_max = None
        if lat_n:
            mean = sum(self._lat_sum[s] for s in live) / lat_n / 1e6
            lat_max = max(self._lat_max[s] for s in live if self._lat_n[s]) / 1e6
            p50 = self._percentile(0.50, lat_n) / 1e6
            p99 = min(self._percentile(0.99, lat_n) / 1e6, lat_max)
        newest_age = None
        if self._newest_send_ns is not None and offset is not None:
            newest_age = (now_ns - (self._newest_send_ns - offset)) / 1e6
        return LinkSnapshot(
            window_s=self.window_s,
            received=received,
            lost=lost,
            loss_rate=lost / (received + lost) if received + lost else 0.0,
            duplicates=sum(self._dup[s] for s in live),
            reordered=sum(self._reordered[s] for s in live),
            loss_bursts=bursts,
            max_loss_burst=max((self._burst_max[s] for s in live), default=0),
            mean_loss_burst=sum(self._burst_sum[s] for s in live) / bursts if bursts else 0.0,
            latency_mean_ms=mean,
            latency_p50_ms=p50,
            latency_p99_ms=p99,
            latency_max_ms=lat_max,
            jitter_ms=self._jitter_ns / 1e6,
            since_last_ms=(now_ns - self._last_recv_ns) / 1e6
            if self._last_recv_ns is not None
            else None,
            newest_age_ms=newest_age,
            clock_offset_ms=offset / 1e6 if offset is not None else None,
            clock_uncertainty_ms=est.uncertainty_ns / 1e6 if est is not None else None,
        )

    def _percentile(self, q: float, n: int) -> float:
        target = q * n
        acc = 0
        for i, c in enumerate(self._window_hist):
            acc += c
            if acc >= target and c:
                return _bin_value_ns(i)
        return _bin_value_ns(_HIST_BINS - 1)
