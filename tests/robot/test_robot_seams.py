"""The robot node and the serial driver driven through their seams, as the bench drives them."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from common.clocks.clock import VirtualClock
from common.wire.transport import CaptureLink
from harness.bench.fixtures import frame_set, scan_bytes, serial_sensor
from robot_side.node import RobotNode
from robot_side.node.config import RobotConfig

pytestmark = pytest.mark.slow


def test_bytes_fed_to_the_serial_driver_become_a_frame_the_node_renders() -> None:
    frame = frame_set(1, seed=2).frames[0]
    sensor = serial_sensor()
    data = scan_bytes(frame, 7)
    sensor.feed(data[:50], 1_000)  # a scan split across reads, as a port delivers it
    assert sensor.latest() is None
    sensor.feed(data[50:], 2_000)
    sample = sensor.latest()
    assert sample is not None and sample.t_capture_ns == 2_000
    np.testing.assert_allclose(sample.frame, frame, atol=0.01)

    config = RobotConfig()
    config.render.mode = "direct"
    clock, link = VirtualClock(t_ns=2_000), CaptureLink()
    node = RobotNode(config, sensor, now=clock, link=link)
    sent = node.process(sample)
    assert sent is not None and link.messages == [sent] and node.last_stimulus is sent
    assert sent.t_send_ns == 2_000  # the node's clock is the one it was handed
    clock.advance(round(config.max_frame_age_ms * 1e6) + 1)
    assert node.process(sample) is None and node.counters["frames_stale"] == 1


def test_a_node_handed_a_link_refuses_to_run() -> None:
    config = RobotConfig()
    config.render.mode = "direct"
    node = RobotNode(config, None, link=CaptureLink())
    with pytest.raises(RuntimeError, match="handed a link"):
        node.run(threading.Event())
