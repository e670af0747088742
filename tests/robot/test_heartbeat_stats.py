"""The robot's counters past the protocol's limit of a heartbeat's map take turns."""

from __future__ import annotations

import math

from common.wire.codec import MAX_STATS
from robot_side.node.telemetry import STATE_KEYS, Telemetry


def test_past_the_limit_every_counter_comes_within_a_few_heartbeats_the_state_in_each():
    counters = {f"link_{i}": float(i) for i in range(3)} | dict.fromkeys(STATE_KEYS, 1.0)
    counters |= {f"count_{i:03d}": float(i) for i in range(MAX_STATS + 20)}
    always = {"link_0", "link_1", "link_2", *STATE_KEYS}
    telemetry = Telemetry(
        None, name=b"cell1", session=1, now=lambda: 0, stats=lambda: dict(counters), counters={}
    )
    others = len(counters) - len(always)
    turns = math.ceil(others / (MAX_STATS - len(always)))
    kept: dict[str, float] = {}
    for _ in range(turns):
        beat = telemetry._heartbeat_stats()
        assert len(beat) == MAX_STATS
        assert always <= beat.keys()  # the state an operator acts on, and the links' health
        kept |= beat  # as an operator keeps them: each counter's newest value
    assert kept == counters


def test_within_the_limit_every_heartbeat_carries_them_all():
    counters = {f"count_{i}": float(i) for i in range(MAX_STATS)}
    telemetry = Telemetry(
        None, name=b"cell1", session=1, now=lambda: 0, stats=lambda: dict(counters), counters={}
    )
    assert telemetry._heartbeat_stats() == counters
