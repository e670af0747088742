"""A starved operator loop counts its late wake-ups and how late (its stats: the status file the
fault matrix reads), and says so in its log."""

from __future__ import annotations

import logging
import threading
import time

from common.wire.transport import free_loopback_ports
from operator_side.node import OperatorNode
from operator_side.node.config import OperatorConfig
from operator_side.servos.in_memory import InMemoryServoBus


def test_a_loop_that_wakes_300_ms_late_is_counted_with_how_late(caplog):
    tel, cmd = (f"tcp://127.0.0.1:{p}" for p in free_loopback_ports(2))
    config = OperatorConfig()
    config.link.telemetry_endpoint, config.link.command_endpoint = tel, cmd
    starved = threading.Event()
    skew = {"ns": 0}

    def clock() -> int:
        # from then on the clock reads 300 ms on: the loop "slept" that much longer than asked
        if starved.is_set():
            skew["ns"] = 300_000_000
        return time.monotonic_ns() + skew["ns"]

    bus = InMemoryServoBus()
    node = OperatorNode(config, bus, now=clock)
    stop = threading.Event()
    with caplog.at_level(logging.WARNING, logger="operator_side.node"):
        thread = threading.Thread(target=node.run, args=(stop, 1.0))
        thread.start()
        time.sleep(0.3)
        starved.set()
        thread.join(timeout=5)
    assert not thread.is_alive()
    stats = node.stats()
    late = [r for r in caplog.records if "after its deadline" in r.getMessage()]
    # one for the jump (a loaded machine may starve the loop of its own once more), logged
    # (the first of a burst in full, the rest summed up later)
    assert stats["late_wakes"] >= 1 and late, caplog.text
    assert "the operator's loop" in late[0].getMessage() and "staleness" in late[0].getMessage()
    # each over 100 ms; the jump's 300 ms less what was left of the wait it came in (a
    # heartbeat is due every 50 ms)
    assert stats["late_wake_ms"] >= max(190, 100 * stats["late_wakes"]), (stats, caplog.text)
