"""The impairment engine in virtual time: seeded, and statistically what was configured."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from common.errors import ConfigError
from common.netsim.impairments import (
    DirectionConfig,
    DirectionImpairment,
    LinkCuts,
    unit_quantile,
)
from common.wire.codec import DecodeError, decode, encode
from common.wire.messages import Heartbeat, Stimulus

MS = 1_000_000
PERIOD_NS = 8_333_333  # 120 Hz
PAYLOAD = b"STIM" + msgpack.packb({"seq": 1, "x": b"\0" * 200})


def run(
    config: DirectionConfig,
    n: int,
    *,
    seed: int = 1,
    period_ns: int = PERIOD_NS,
    payload: bytes = PAYLOAD,
) -> tuple[list[tuple[int, int, int, bytes]], DirectionImpairment]:
    """(index, t_in, due, bytes) per delivery."""
    engine = DirectionImpairment(config, seed=seed, name="to_operator")
    out = []
    for i in range(n):
        t = i * period_ns
        for due, data in engine.process(t, payload):
            out.append((i, t, due, data))
    return out, engine


def delays_ms(deliveries) -> np.ndarray:
    return np.array([(due - t) / MS for _, t, due, _ in deliveries])


# ---------------------------------------------------------------- determinism
configs = st.builds(
    DirectionConfig,
    delivery=st.just("datagram"),
    delay_ms=st.floats(0, 200),
    jitter_ms=st.floats(0, 50),
    distribution=st.sampled_from(["uniform", "normal", "pareto", "paretonormal"]),
    delay_correlation=st.floats(0, 0.95),
    loss_percent=st.floats(0, 50),
    loss_correlation=st.floats(0, 0.9),
    duplicate_percent=st.floats(0, 20),
    reorder_percent=st.floats(0, 20),
    corrupt_percent=st.floats(0, 20),
    rate_kbit=st.sampled_from([0.0, 500.0, 5000.0]),
)


@settings(max_examples=25, deadline=None)
@given(config=configs, seed=st.integers(0, 2**32))
def test_same_seed_same_sequence_and_never_early(config: DirectionConfig, seed: int) -> None:
    a, _ = run(config, 300, seed=seed)
    b, _ = run(config, 300, seed=seed)
    assert a == b
    assert all(due >= t for _, t, due, _ in a)


def test_different_seeds_differ() -> None:
    config = DirectionConfig(delivery="datagram", delay_ms=20, jitter_ms=5, loss_percent=10)
    assert run(config, 200, seed=1)[0] != run(config, 200, seed=2)[0]


def test_changing_loss_leaves_the_delay_sequence_alone() -> None:
    base = {"delivery": "datagram", "delay_ms": 30, "jitter_ms": 8, "distribution": "normal"}
    clean, _ = run(DirectionConfig(**base), 2000)
    lossy, _ = run(DirectionConfig(**base, loss_percent=20), 2000)
    clean_by_index = {i: due - t for i, t, due, _ in clean}
    assert len(lossy) < len(clean)
    assert all(clean_by_index[i] == due - t for i, t, due, _ in lossy)


# ---------------------------------------------------------------- delay
@pytest.mark.parametrize("dist", ["uniform", "normal", "pareto", "paretonormal"])
def test_delay_percentiles_match_the_configured_distribution(dist: str) -> None:
    config = DirectionConfig(
        delivery="datagram", delay_ms=60, jitter_ms=10, distribution=dist, delay_correlation=0.3
    )
    d = delays_ms(run(config, 10_000)[0])
    for q in (0.05, 0.5, 0.9, 0.99):
        want = config.delay_quantile_ms(q)
        assert abs(np.quantile(d, q) - want) <= max(0.5, 0.05 * want), (q, want)


def test_empirical_table() -> None:
    table = [1.0, 2.0, 2.5, 4.0, 12.0, 30.0]
    config = DirectionConfig(
        delivery="datagram", delay_ms=10, distribution="table", delay_table_ms=table
    )
    d = delays_ms(run(config, 10_000)[0])
    assert d.min() >= 11.0 - 1e-6 and d.max() <= 40.0 + 1e-6
    assert abs(np.median(d) - config.delay_quantile_ms(0.5)) < 0.5


def test_netem_shapes() -> None:
    assert unit_quantile("uniform", 0.0) == -1.0 and unit_quantile("uniform", 1.0) == 1.0
    assert unit_quantile("pareto", 0.0) == pytest.approx(-2 / 3)
    assert unit_quantile("pareto", 0.999) == 4.0  # netem clips its table at 4 sigma
    us = (np.arange(100_000) + 0.5) / 100_000
    assert abs(np.mean([unit_quantile("normal", u) for u in us])) < 1e-3


def test_delay_correlation_is_lag_one_autocorrelation() -> None:
    config = DirectionConfig(
        delivery="datagram", delay_ms=50, jitter_ms=10, distribution="normal", delay_correlation=0.7
    )
    d = delays_ms(run(config, 10_000)[0])
    r = np.corrcoef(d[:-1], d[1:])[0, 1]
    assert abs(r - 0.7) < 0.03
    assert abs(d.std() - 10) < 0.6  # correlation must not narrow the distribution


# ---------------------------------------------------------------- loss
def _loss_runs(received_idx: set[int], n: int) -> tuple[float, float]:
    lost = np.array([i not in received_idx for i in range(n)])
    runs, k = [], 0
    for x in lost:
        if x:
            k += 1
        elif k:
            runs.append(k)
            k = 0
    if k:
        runs.append(k)
    return float(lost.mean()), float(np.mean(runs)) if runs else 0.0


@pytest.mark.parametrize(
    "kwargs",
    [
        {"loss_percent": 5.0},
        {"loss_percent": 5.0, "loss_correlation": 0.6},
        {
            "loss_model": "gilbert_elliott",
            "ge_p_percent": 1.0,
            "ge_r_percent": 25.0,
            "ge_loss_bad_percent": 90.0,
            "ge_loss_good_percent": 0.5,
        },
    ],
)
def test_loss_rate_and_burst_length(kwargs) -> None:
    config = DirectionConfig(delivery="datagram", **kwargs)
    n = 50_000
    out, engine = run(config, n, payload=b"STIM\x80")
    rate, burst = _loss_runs({i for i, *_ in out}, n)
    assert abs(rate - config.loss_rate()) < 0.005
    assert abs(burst - config.mean_loss_burst()) < 0.1 * config.mean_loss_burst()
    assert engine.counts.lost == n - len(out)


# ---------------------------------------------------------------- dup, reorder, corrupt
def test_duplication_rate() -> None:
    config = DirectionConfig(delivery="datagram", delay_ms=5, jitter_ms=1, duplicate_percent=4)
    out, engine = run(config, 20_000)
    extra = len(out) - 20_000
    assert abs(extra / 20_000 - 0.04) < 0.005
    assert engine.counts.duplicated == extra


def test_reordered_messages_overtake() -> None:
    config = DirectionConfig(delivery="datagram", delay_ms=40, reorder_percent=10)
    out, engine = run(config, 10_000)
    assert abs(engine.counts.reordered / 10_000 - 0.10) < 0.01
    arrival = [i for i, _, _, _ in sorted(out, key=lambda r: (r[2], r[0]))]
    late = sum(1 for k in range(1, len(arrival)) if arrival[k] < max(arrival[:k][-8:]))
    assert late > 0.5 * engine.counts.reordered


def _wire_messages() -> list[bytes]:
    stim = Stimulus(
        seq=7,
        t_send_ns=123,
        t_capture_ns=100,
        frame_seq=3,
        mode="mask",
        contact=True,
        stimulus=np.zeros((3, 3), np.float32),
        pattern=2,
        confidence=0.9,
    )
    hb = Heartbeat(seq=1, t_send_ns=5, node="robot", state="ok", echo_t_send_ns=4, echo_t_recv_ns=6)
    return [encode(stim), encode(hb)]


@pytest.mark.parametrize("wire", _wire_messages())
def test_truncation_is_always_rejected_by_the_decoder(wire: bytes) -> None:
    decode(wire)  # the intact message is fine
    config = DirectionConfig(delivery="datagram", corrupt_percent=100)
    out, engine = run(config, 500, payload=wire)
    assert engine.counts.corrupted == 500
    for *_, data in out:
        assert data[:4] == wire[:4] and len(data) < len(wire)
        with pytest.raises(DecodeError):
            decode(data)


@settings(max_examples=200, deadline=None)
@given(
    body=st.dictionaries(
        st.text(max_size=8),
        st.one_of(
            st.integers(-(2**63), 2**64 - 1),
            st.floats(allow_nan=False),
            st.binary(max_size=40),
            st.lists(st.integers(-1000, 1000), max_size=5),
            st.none(),
            st.booleans(),
        ),
        min_size=1,
        max_size=8,
    ),
    u=st.floats(0, 1, exclude_max=True),
)
@pytest.mark.slow
@pytest.mark.untimed  # arithmetic on given numbers: no clock
def test_any_truncated_msgpack_map_fails_to_unpack(body: dict, u: float) -> None:
    from common.netsim.impairments import _corrupt

    wire = b"STIM" + msgpack.packb(body)
    damaged = _corrupt(wire, u, "truncate")
    with pytest.raises(Exception):  # noqa: B017 - msgpack raises several types
        msgpack.unpackb(damaged[4:])


def test_bitflip_changes_exactly_one_bit_of_the_body() -> None:
    config = DirectionConfig(delivery="datagram", corrupt_percent=100, corrupt_mode="bitflip")
    out, _ = run(config, 200)
    for *_, data in out:
        diff = [a ^ b for a, b in zip(data, PAYLOAD, strict=True)]
        assert diff[:4] == [0, 0, 0, 0]
        assert sum(bin(x).count("1") for x in diff) == 1


# ---------------------------------------------------------------- rate, outage, delivery
def test_rate_limit_spaces_messages_and_tail_drops() -> None:
    payload = b"FRAM" + b"\0" * 996  # 1000 bytes = 8 kbit
    config = DirectionConfig(delivery="datagram", rate_kbit=400, queue_limit=10)  # 20 ms each
    out, engine = run(config, 500, period_ns=10 * MS, payload=payload)  # offered twice the rate
    dues = [due for _, _, due, _ in out]
    assert min(np.diff(dues)) >= 20 * MS
    assert engine.counts.queue_dropped > 200  # about half cannot fit
    assert max(due - t for _, t, due, _ in out) <= 11 * 20 * MS


def test_outage_datagram_drops_exactly_the_window() -> None:
    config = DirectionConfig(delivery="datagram", delay_ms=10, outages=[(1.0, 1.5)])
    out, engine = run(config, 240)  # 2 s at 120 Hz
    got = {t for _, t, _, _ in out}
    for i in range(240):
        t = i * PERIOD_NS
        assert (t in got) == (not 1e9 <= t < 1.5e9)
    assert engine.counts.outage_dropped == 60


def test_outage_stream_delivers_everything_late_and_in_order() -> None:
    config = DirectionConfig(
        delivery="stream", delay_ms=10, retransmit_ms=200, outages=[(1.0, 1.5)]
    )
    out, engine = run(config, 240)
    assert [i for i, *_ in out] == list(range(240))
    dues = [due for _, _, due, _ in out]
    assert dues == sorted(dues)
    first_in_outage = next(r for r in out if r[1] >= 1e9)
    # Resent at +200, +600 ms: 1.6 s is the first attempt after the link is back.
    assert first_in_outage[2] == first_in_outage[1] + 600 * MS + 10 * MS
    assert engine.counts.retransmitted == 60


def test_a_cut_while_running_is_an_outage_in_either_delivery_model() -> None:
    """A pulled cable (``LinkCuts``, netsim's SIGUSR1) drops what a datagram link carries
    through it and makes a stream's bytes wait for the retransmission after it, as a
    scheduled outage does; both directions share it."""
    for delivery in ("datagram", "stream"):
        cuts = LinkCuts()
        config = DirectionConfig(delivery=delivery, delay_ms=10, retransmit_ms=200)
        engines = [DirectionImpairment(config, name=n, cuts=cuts) for n in ("a", "b")]
        cuts.add(round(1e9), round(1.5e9))
        for engine in engines:
            out = [(t, engine.process(t, PAYLOAD)) for t in range(0, round(2e9), PERIOD_NS)]
            if delivery == "datagram":
                assert all((not d) == (1e9 <= t < 1.5e9) for t, d in out)
                assert engine.counts.outage_dropped == 60
            else:
                first_in_cut = next(d[0][0] - t for t, d in out if t >= 1e9)
                assert first_in_cut == 600 * MS + 10 * MS  # resent at +200, +600 ms
                assert all(d for _, d in out)  # nothing lost


def test_stream_never_loses_and_blocks_the_head_of_line() -> None:
    stream = DirectionConfig(delivery="stream", delay_ms=20, loss_percent=5, retransmit_ms=100)
    out, engine = run(stream, 10_000)
    assert [i for i, *_ in out] == list(range(10_000))
    d = delays_ms(out)
    assert abs(engine.counts.retransmitted / 10_000 - 0.05) < 0.01
    assert (d >= 120 - 1e-9).sum() >= engine.counts.retransmitted
    assert engine.counts.held_back > engine.counts.retransmitted  # followers wait too

    datagram = DirectionConfig(delivery="datagram", delay_ms=20, loss_percent=5)
    out, _ = run(datagram, 10_000)
    assert abs(1 - len(out) / 10_000 - 0.05) < 0.01
    assert np.all(delays_ms(out) == 20)


def test_stream_refuses_impairments_tcp_cannot_show() -> None:
    with pytest.raises(ConfigError, match="stream"):
        DirectionConfig(delivery="stream", duplicate_percent=1)
    with pytest.raises(ConfigError, match=r"0\.\.100"):
        DirectionConfig(loss_percent=120)
    with pytest.raises(ConfigError, match="delay_table_ms"):
        DirectionConfig(distribution="table")
