"""A starved operator loop says so in its log, in the words the fault matrix reads."""

from __future__ import annotations

import logging
import threading
import time

from common.transport import free_loopback_ports
from harness.faults.deployment import late_wakes_in
from operator_side.config import OperatorConfig
from operator_side.node import OperatorNode
from operator_side.servos.recording import RecordingServoBus


def test_a_loop_that_wakes_300_ms_late_is_logged_with_when_it_was_due_and_woke(caplog):
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

    bus = RecordingServoBus()
    node = OperatorNode(config, bus, now=clock)
    stop = threading.Event()
    with caplog.at_level(logging.WARNING, logger="operator_side.node"):
        thread = threading.Thread(target=node.run, args=(stop, 1.0))
        thread.start()
        time.sleep(0.3)
        starved.set()
        thread.join(timeout=5)
    assert not thread.is_alive()
    wakes = late_wakes_in(caplog.text)
    # one for the jump (a loaded machine may starve the loop of its own once more)
    assert node.counters["late_wakes"] == len(wakes) >= 1, caplog.text
    # 300 ms less what was left of the wait the jump came in (a heartbeat is due every 50 ms)
    assert any(0.19 <= woke - due < 0.5 for due, woke in wakes), wakes
