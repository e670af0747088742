"""The offset between this machine's monotonic clock and the peer's, from heartbeats.

Each node's timestamps are its own ``time.monotonic_ns``, whose origin is
arbitrary (boot time), so a remote timestamp means nothing here until the
offset between the two clocks is known. Heartbeats carry what NTP's
on-wire protocol needs. When a heartbeat arrives from the peer:

- ``t1 = echo_t_send_ns``: when we sent the heartbeat it echoes (our clock)
- ``t2 = echo_t_recv_ns``: when the peer received that one (peer's clock)
- ``t3 = t_send_ns``: when the peer sent this one (peer's clock)
- ``t4``: when we received this one (our clock)

offset = ((t2 - t1) + (t3 - t4)) / 2 is peer minus local, and
delay = (t4 - t1) - (t3 - t2) is the round trip without the peer's hold
time. Each sample's error is half the difference of its two one-way
delays, so at most half its round trip, and smallest when both were close
to their floor (propagation, no queueing). Like NTP's clock filter, the
estimate trusts the samples with the smallest round trips among the recent
ones; it takes the median offset of the ``best`` few of them rather than
the single best, which halves the noise without letting queueing in, and
charges each sample for its age at an assumed drift so fresh samples
eventually win over old lucky ones.

What no round-trip method can see is a fixed asymmetry of the path: if
one direction is always 2 ms slower, the offset is off by 1 ms and the
uncertainty still covers it only because it is half the round trip.
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass

from common.errors import LinkError

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class OffsetSample:
    """One round trip's reading of the clock offset."""

    t_local_ns: int  # t4: when it was taken, our clock
    offset_ns: int  # peer minus local
    delay_ns: int  # round trip, peer's hold time excluded


@dataclass(frozen=True, slots=True)
class ClockEstimate:
    """The current best offset and how far from the truth it can be."""

    offset_ns: int  # peer minus local: local = remote - offset
    uncertainty_ns: int  # half the best round trip + drift since it + spread of the chosen
    delay_ns: int  # that sample's round trip
    age_ns: int  # how old that sample is
    samples: int  # how many samples are in the window


#: How far back a late heartbeat may be stamped and still count as reordered.
REORDER_WINDOW_NS = 1_000_000_000


class ClockSync:
    """Estimates the peer's clock offset from heartbeat round trips (NTP-style).

    Also remembers the peer's latest heartbeat so the node can echo it:
    put ``echo_fields()`` into every outgoing heartbeat.
    """

    def __init__(
        self,
        *,
        window: int = 64,
        best: int = 5,
        max_age_s: float = 60.0,
        drift_ppm: float = 15.0,
    ) -> None:
        if window < 1 or best < 1:
            raise ValueError(f"window and best must be >= 1, not {window} and {best}")
        self.window = window
        self.best = best
        self.max_age_ns = round(max_age_s * 1e9)
        #: NTP's PHI: how fast an old sample's error bound grows (15 ppm).
        self.drift_ppm = drift_ppm
        self._samples: deque[OffsetSample] = deque(maxlen=window)
        self._cached_offset_ns: int | None = None  # best as of the newest sample
        self._peer_t_send_ns: int | None = None
        self._peer_t_recv_ns: int | None = None
        self._last_key: tuple[int, int, int] | None = None
        self.accepted = 0
        self.rejected = 0

    def reset(self) -> None:
        """Forget every sample: the peer restarted, maybe on another clock (a new boot id)."""
        self._samples.clear()
        self._cached_offset_ns = None
        self._peer_t_send_ns = self._peer_t_recv_ns = None
        self._last_key = None

    # ------------------------------------------------------------ input
    def on_heartbeat(
        self,
        t_send_ns: int,
        echo_t_send_ns: int | None,
        echo_t_recv_ns: int | None,
        t_recv_ns: int,
    ) -> bool:
        """Take in a peer heartbeat's timestamps and our receive time.

        Returns whether it yielded a usable offset sample (a heartbeat that
        echoes nothing yet, a duplicate or an impossible one does not).
        """
        newest = self._peer_t_send_ns
        # Echo the newest heartbeat. One sent up to a second before the newest
        # is a reordering and ignored; one far older means the newest was
        # bogus (a corrupted, future stamp) or the peer restarted its clock.
        if newest is None or t_send_ns > newest or t_send_ns < newest - REORDER_WINDOW_NS:
            self._peer_t_send_ns = t_send_ns
            self._peer_t_recv_ns = t_recv_ns
        if echo_t_send_ns is None or echo_t_recv_ns is None:
            return False
        return self.add_sample(echo_t_send_ns, echo_t_recv_ns, t_send_ns, t_recv_ns)

    def add_sample(self, t1: int, t2: int, t3: int, t4: int) -> bool:
        """One NTP exchange: t1, t4 on our clock; t2, t3 on the peer's."""
        key = (t1, t2, t3)
        if key == self._last_key:
            return False  # the same heartbeat twice (duplicated on the link)
        delay = (t4 - t1) - (t3 - t2)
        if delay < 0 or t3 < t2 or t4 < t1:
            self.rejected += 1
            log.debug("impossible clock sample t1..t4 = %d %d %d %d", t1, t2, t3, t4)
            return False
        self._last_key = key
        offset = ((t2 - t1) + (t3 - t4)) // 2
        self._samples.append(OffsetSample(t4, offset, delay))
        self.accepted += 1
        self._cached_offset_ns = None
        return True

    def echo_fields(self) -> tuple[int | None, int | None]:
        """``(echo_t_send_ns, echo_t_recv_ns)`` for our next heartbeat."""
        return self._peer_t_send_ns, self._peer_t_recv_ns

    # ------------------------------------------------------------ output
    def _bound(self, s: OffsetSample, now_ns: int) -> float:
        return s.delay_ns / 2 + self.drift_ppm * 1e-6 * max(0, now_ns - s.t_local_ns)

    def estimate(self, now_ns: int | None = None) -> ClockEstimate | None:
        """The best current estimate, or None before the first sample (or when all are too old)."""
        if not self._samples:
            return None
        if now_ns is None:
            now_ns = self._samples[-1].t_local_ns
        while self._samples and now_ns - self._samples[0].t_local_ns > self.max_age_ns:
            self._samples.popleft()
            self._cached_offset_ns = None
        if not self._samples:
            return None
        ranked = sorted(self._samples, key=lambda s: self._bound(s, now_ns))
        top = sorted(s.offset_ns for s in ranked[: self.best])
        offset = top[len(top) // 2]
        best = ranked[0]
        # The truth is within the best sample's bound of its offset, so
        # within that plus the distance to the median of the chosen few.
        uncertainty = self._bound(best, now_ns) + abs(offset - best.offset_ns)
        return ClockEstimate(
            offset_ns=offset,
            uncertainty_ns=round(uncertainty),
            delay_ns=best.delay_ns,
            age_ns=now_ns - best.t_local_ns,
            samples=len(self._samples),
        )

    @property
    def is_synced(self) -> bool:
        return bool(self._samples)

    @property
    def offset_ns(self) -> int | None:
        """Peer minus local, per the best sample as of the newest one (None before any).

        Cached until the next sample, so converting every message at 60 Hz
        costs nothing.
        """
        if self._cached_offset_ns is None:
            est = self.estimate()
            if est is None:
                return None
            self._cached_offset_ns = est.offset_ns
        return self._cached_offset_ns

    def to_local(self, t_remote_ns: int) -> int:
        """A peer timestamp on our clock; raises ``LinkError`` before the first sample."""
        offset = self.offset_ns
        if offset is None:
            raise LinkError("no clock offset yet: no heartbeat round trip has completed")
        return t_remote_ns - offset

    def to_remote(self, t_local_ns: int) -> int:
        """One of our timestamps on the peer's clock."""
        offset = self.offset_ns
        if offset is None:
            raise LinkError("no clock offset yet: no heartbeat round trip has completed")
        return t_local_ns + offset
