"""The simulator forwards raw bytes both ways over real sockets, on time."""

from __future__ import annotations

import statistics
import time

import pytest

from common.netsim.impairments import DirectionConfig, Scenario
from operator_side.node.config import OperatorLinkConfig


def _fixed(to_operator_ms: float, to_robot_ms: float) -> Scenario:
    return Scenario(
        name="fixed",
        to_operator=DirectionConfig(delay_ms=to_operator_ms),
        to_robot=DirectionConfig(delay_ms=to_robot_ms),
    )


def test_forwards_both_directions_unchanged(make_link) -> None:
    link = make_link()
    link.robot_pub.send(b"STIM\x81\xa1a\x01")
    assert link.recv(link.operator_sub) == b"STIM\x81\xa1a\x01"
    link.operator_pub.send(b"CMND\x80")
    assert link.recv(link.robot_sub) == b"CMND\x80"
    c = link.sim.counters()
    assert c["to_operator"]["sent"] >= 1 and c["to_robot"]["sent"] >= 1


def _one_way_ms(link, pub, sub, n: int = 30) -> list[float]:
    out = []
    for i in range(n):
        t0 = time.monotonic_ns()
        sent = b"HBRT" + i.to_bytes(4, "little")
        pub.send(sent)
        data = link.recv(sub)
        while data is not None and data.startswith(b"PRBE"):  # a join probe that came late
            data = link.recv(sub)
        assert data == sent, f"message lost on a lossless link (got {data!r})"
        out.append((time.monotonic_ns() - t0) / 1e6)
    return out


def test_fixed_delay_per_direction(make_link) -> None:
    link = make_link(_fixed(30.0, 5.0))
    down = _one_way_ms(link, link.robot_pub, link.operator_sub, 15)
    up = _one_way_ms(link, link.operator_pub, link.robot_sub, 15)
    # Never early, on any machine; each direction its own delay (the commands' 5 ms, not the
    # telemetry's 30). How late beyond it on a quiet machine is the bench's figure
    # (python -m harness.bench.netsim_engine, own cost); here at most the operator's
    # staleness limit, which a busy machine's scheduling stays far inside.
    late = OperatorLinkConfig().stale_after_ms
    assert min(down) >= 30.0 and statistics.median(down) < 30.0 + late, down
    assert min(up) >= 5.0 and statistics.median(up) < 30.0, up


@pytest.mark.slow
def test_stop_is_prompt_and_idempotent(make_link) -> None:
    link = make_link(_fixed(500.0, 500.0))
    link.robot_pub.send(b"STIM\x80")  # still in flight when we stop
    t0 = time.monotonic()
    link.sim.stop()
    link.sim.stop()
    assert time.monotonic() - t0 < 0.5
    assert not link.sim.is_running


@pytest.mark.slow
def test_outage_on_real_sockets(make_link) -> None:
    from common.netsim.scenario import scenario_from_dict

    scenario = scenario_from_dict(
        {"name": "cut", "both": {"delivery": "datagram", "outages": [[1.0, 1.5]]}}
    )
    link = make_link(scenario)
    start = link.sim.start_ns
    sent = {}
    seq = 0
    while time.monotonic_ns() - start < 2.0e9:
        seq += 1
        sent[seq] = time.monotonic_ns() - start
        link.robot_pub.send(b"STIM" + seq.to_bytes(4, "little"))
        time.sleep(0.01)
    got = set()
    while (data := link.recv(link.operator_sub, 0.2)) is not None:
        got.add(int.from_bytes(data[4:8], "little"))
    margin = 0.02e9  # loopback transit either side of the edges
    inside = 0
    for s, t in sent.items():
        if 1.0e9 + margin < t < 1.5e9 - margin:
            inside += 1
            assert s not in got, f"message sent {t / 1e9:.3f} s in crossed the outage"
        elif t < 1.0e9 - margin or t > 1.5e9 + margin:
            assert s in got, f"message sent {t / 1e9:.3f} s in was lost outside the outage"
    # counted by when each was sent: a busy machine's sender falls behind its 10 ms pace
    assert inside > 0 and link.sim.counters()["to_operator"]["outage_dropped"] >= inside


def test_corrupted_messages_are_rejected_by_the_operator_decoder(make_link) -> None:
    import numpy as np
    import zmq

    from common.netsim.scenario import scenario_from_dict
    from common.wire.codec import encode
    from common.wire.messages import Stimulus
    from common.wire.transport import Subscriber

    scenario = scenario_from_dict(
        {"name": "dirty", "both": {"delivery": "datagram", "corrupt_percent": 50}}
    )
    link = make_link(scenario, seed=5)
    ctx = zmq.Context()
    sub = Subscriber(ctx, link.sim.operator_telemetry_endpoint, bind=False)
    try:
        t_end = time.monotonic() + 5.0  # slow joiner: probe until the subscription is up
        while sub.received == 0 and time.monotonic() < t_end:
            link.robot_pub.send(b"PRBE\x80")
            sub.poll(0.02)
            sub.drain()
        time.sleep(0.1)
        sub.drain()
        received0, rejected0 = sub.received, sub.rejected_total
        corrupted0 = link.sim.counters()["to_operator"]["corrupted"]
        for seq in range(200):
            stim = Stimulus(
                seq=seq,
                t_send_ns=time.monotonic_ns(),
                t_capture_ns=0,
                frame_seq=seq,
                mode="direct",
                contact=False,
                stimulus=np.zeros((3, 3), np.float32),
            )
            link.robot_pub.send(encode(stim))
            time.sleep(0.001)
        valid = []
        t_end = time.monotonic() + 5.0
        while sub.received - received0 < 200 and time.monotonic() < t_end:
            sub.poll(0.05)
            valid += sub.drain()
        corrupted = link.sim.counters()["to_operator"]["corrupted"] - corrupted0
        assert sub.received - received0 == 200
        assert 60 < corrupted < 140
        # Every damaged one is rejected, and only those.
        assert sub.rejected_total - rejected0 == corrupted
        assert len(valid) == 200 - corrupted
    finally:
        sub.close()
        ctx.destroy(linger=0)


def test_a_burst_larger_than_one_read_batch_all_arrives_in_order(make_link) -> None:
    link = make_link()
    n = 800  # more than the proxy reads per batch, within every high-water mark
    for i in range(n):
        link.robot_pub.send(b"STIM" + i.to_bytes(4, "little"))
    got = []
    while len(got) < n and (data := link.recv(link.operator_sub, 2.0)) is not None:
        got.append(int.from_bytes(data[4:8], "little"))
    assert got == list(range(n))
