"""The frame loop says why a stimulus was late: a starved wake or a slow phase, with its time."""

from __future__ import annotations

import logging
import time
from collections import Counter

from common.clocks.clock import now_ns
from common.clocks.late_wake import LATE_WAKE_NS
from robot_side.node.loop_watch import SLOW_TURN_NS, LoopWatch


def test_a_late_wake_and_a_slow_phase_are_counted_and_named(caplog):
    counters: Counter[str] = Counter()
    watch = LoopWatch(counters)
    with caplog.at_level(logging.WARNING, logger="robot_side.node.loop_watch"):
        t = now_ns()
        watch.woke(t - LATE_WAKE_NS - 50_000_000, t)  # 150 ms after its deadline
        watch.mark("receive")
        time.sleep(SLOW_TURN_NS / 1e9 + 0.02)
        watch.turn_done("frame")
        watch.woke(now_ns(), now_ns())  # on time, and quick
        watch.turn_done("frame")
    assert counters["late_wakes"] == 1 and 140 <= counters["late_wake_ms"] <= 160
    assert counters["slow_turns"] == 1 and counters["slow_turn_ms"] >= SLOW_TURN_NS / 1e6
    text = caplog.text
    assert "woke 150 ms after its deadline" in text
    assert "a turn took" in text and "frame" in text and "receive" in text
