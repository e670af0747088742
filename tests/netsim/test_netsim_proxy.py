"""The simulator forwards raw bytes both ways over real sockets, on time."""

from __future__ import annotations

import statistics
import time

from common.netsim.impairments import DirectionConfig, Scenario


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
        pub.send(b"HBRT" + i.to_bytes(4, "little"))
        data = link.recv(sub)
        assert data is not None, "message lost on a lossless link"
        out.append((time.monotonic_ns() - t0) / 1e6)
    return out


def test_fixed_delay_per_direction(make_link) -> None:
    link = make_link(_fixed(20.0, 5.0))
    down = _one_way_ms(link, link.robot_pub, link.operator_sub, 15)
    up = _one_way_ms(link, link.operator_pub, link.robot_sub, 15)
    # The delay is never early; lateness is loopback plus scheduling noise.
    assert min(down) >= 20.0 and statistics.median(down) < 22.0
    assert min(up) >= 5.0 and statistics.median(up) < 7.0


def test_stop_is_prompt_and_idempotent(make_link) -> None:
    link = make_link(_fixed(500.0, 500.0))
    link.robot_pub.send(b"STIM\x80")  # still in flight when we stop
    t0 = time.monotonic()
    link.sim.stop()
    link.sim.stop()
    assert time.monotonic() - t0 < 0.5
    assert not link.sim.is_running
