"""Receiver statistics agree with what the simulated link did."""

from __future__ import annotations

import numpy as np
import pytest

from common.clocks.clock_sync import ClockSync
from common.netsim.impairments import DirectionConfig, Scenario
from common.netsim.virtual import VirtualLink
from common.wire.link_stats import LinkStats

MS = 1_000_000
PERIOD = 16_666_667  # 60 Hz


def drive(config: DirectionConfig, n: int, *, offset_ns: int = 0, seed: int = 1, stats=None):
    """Send n messages robot -> operator; feed arrivals to LinkStats. Returns (stats, delays)."""
    link = VirtualLink(Scenario(to_operator=config), seed=seed)
    stats = stats or LinkStats(same_clock=offset_ns == 0)
    delays = []
    for seq in range(n):
        t = seq * PERIOD
        for due, _, data in link.deliver_until(t):
            sent_seq = int.from_bytes(data[4:12], "little")
            t_send_remote = sent_seq * PERIOD + offset_ns
            stats.on_message(sent_seq, t_send_remote, due)
            delays.append(due - sent_seq * PERIOD)
        link.send("to_operator", t, b"STIM" + seq.to_bytes(8, "little"))
    return stats, np.array(delays) / MS, n * PERIOD


def test_counts_match_the_engine() -> None:
    config = DirectionConfig(
        delivery="datagram",
        delay_ms=30,
        jitter_ms=15,
        distribution="normal",
        loss_percent=3,
        loss_correlation=0.3,
        duplicate_percent=1,
    )
    stats, _, t_end = drive(config, 3000)  # 50 s, inside the 60 s window
    snap = stats.snapshot(t_end)
    engine_lost = 3000 - snap.received  # every message that never arrived
    assert abs(snap.lost - engine_lost) <= 3  # the last few in flight count as neither
    assert snap.loss_rate == pytest.approx(0.03, abs=0.01)
    assert snap.duplicates > 10
    assert snap.reordered > 50  # 15 ms jitter at 60 Hz reorders often
    assert snap.loss_bursts > 0 and snap.max_loss_burst >= 2


def test_latency_percentiles_and_jitter() -> None:
    config = DirectionConfig(delivery="datagram", delay_ms=40, jitter_ms=5, distribution="normal")
    stats, delays, t_end = drive(config, 3000)
    snap = stats.snapshot(t_end)
    assert snap.latency_p50_ms == pytest.approx(np.median(delays), rel=0.03)
    assert snap.latency_p99_ms == pytest.approx(np.quantile(delays, 0.99), rel=0.03)
    assert snap.latency_mean_ms == pytest.approx(delays.mean(), rel=1e-6)
    # Independent normal delays: E|D1 - D2| = 2 sigma / sqrt(pi) = 5.64 ms.
    assert snap.jitter_ms == pytest.approx(5.64, rel=0.35)


def test_constant_delay_has_no_jitter() -> None:
    stats, _, t_end = drive(DirectionConfig(delivery="datagram", delay_ms=10), 200)
    snap = stats.snapshot(t_end)
    assert snap.jitter_ms == 0 and snap.lost == 0
    assert snap.latency_p50_ms == pytest.approx(10, rel=0.03)


def test_latency_uses_the_clock_offset() -> None:
    clock = ClockSync()
    offset = 7_000 * MS
    clock.add_sample(0, 20 * MS + offset, 20 * MS + offset, 40 * MS)  # symmetric 20 ms
    stats = LinkStats(clock=clock)
    config = DirectionConfig(delivery="datagram", delay_ms=25)
    drive(config, 100, offset_ns=offset, stats=stats)
    snap = stats.snapshot(100 * PERIOD)
    assert snap.latency_p50_ms == pytest.approx(25, rel=0.03)
    assert snap.clock_offset_ms == pytest.approx(7000)
    assert snap.clock_uncertainty_ms == pytest.approx(20, abs=0.1)


def test_unknown_offset_leaves_latency_out() -> None:
    stats = LinkStats(clock=ClockSync())
    stats.on_message(1, 5 * MS, 10 * MS)
    snap = stats.snapshot(11 * MS)
    assert snap.latency_p50_ms is None and snap.newest_age_ms is None
    assert snap.since_last_ms == pytest.approx(1.0)
    assert snap.received == 1


def test_window_forgets_and_staleness_grows() -> None:
    stats = LinkStats(same_clock=True, window_s=10.0)
    for seq in range(100):
        stats.on_message(seq, seq * PERIOD, seq * PERIOD + 5 * MS)
    last = 99 * PERIOD + 5 * MS
    assert stats.snapshot(last).received == 100
    later = stats.snapshot(last + 30 * 10**9)
    assert later.received == 0 and later.latency_p50_ms is None
    assert later.since_last_ms == pytest.approx(30_000)
    assert later.newest_age_ms == pytest.approx(30_005)


def test_gap_then_late_arrival_is_reordering_not_loss() -> None:
    stats = LinkStats(same_clock=True)
    for seq in (0, 1, 3, 4, 2, 2, 5):
        stats.on_message(seq, seq * MS, seq * MS + MS)
    snap = stats.snapshot(10 * MS)
    assert (snap.received, snap.lost, snap.reordered, snap.duplicates) == (6, 0, 1, 1)


def test_sender_restart_is_not_a_million_losses() -> None:
    stats = LinkStats(same_clock=True)
    stats.on_message(5_000_000, 0, MS)
    stats.on_message(0, MS, 2 * MS)
    stats.on_message(1, 2 * MS, 3 * MS)
    assert stats.snapshot(4 * MS).lost == 0
