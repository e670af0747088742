"""The robot's video media through the link simulator's datagram mode, seen from a viewer.

An aiortc viewer in this process speaks the video server's own signalling;
the server runs with ``link_scenario`` as ``deepxpalm demo --scenario`` sets
it. The viewer is told only the simulator's port, so every frame it decodes
crossed the simulator, which counts them. How much the scenario adds to
the glass-to-glass time beside a direct viewer only a quiet machine can
judge: ``deepxpalm bench --only video_netsim`` plays the page through each
scenario and gives metro's row a verdict against the direct one. Here the
picture through the simulator stays fresh by the dashboard's own limit.
"""

from __future__ import annotations

import asyncio
import re

import numpy as np
import pytest

pytest.importorskip("aiortc")

from harness.bench.video import ViewerRun, view
from operator_side.dashboard.config import DashboardConfig
from robot_side.camera.config import TestPatternConfig
from robot_side.camera.test_pattern import TestPatternCamera
from robot_side.video.server import VideoConfig, VideoServer

pytestmark = pytest.mark.timeout(90)


def _watch(scenario: str, seconds: float) -> tuple[ViewerRun, dict, list[str]]:
    """A viewer of a server whose media crosses ``scenario`` ("" = direct)."""
    source = TestPatternCamera(TestPatternConfig(width=320, height=240, fps=15))
    config = VideoConfig(port=0, link_scenario=scenario)
    answers: list[str] = []
    with VideoServer(source, config) as server:
        run = ViewerRun()
        counters: dict = {}

        async def watch() -> None:
            task = asyncio.ensure_future(view(server.url, seconds, run))
            while not task.done():
                await asyncio.sleep(0.2)
                for path in list(server.viewing.media_paths):  # while the viewer is connected
                    counters.update(path.counters())
                    answers[:] = [f"{r.address[1]}" for r in path.relays.values()]
            await task

        asyncio.run(watch())
    return run, counters, answers


@pytest.mark.slow
def test_every_frame_the_viewer_decodes_crossed_the_simulator_and_is_fresh():
    direct, none_counters, _ = _watch("", 1.5)
    run, counters, relay_ports = _watch("metro", 3.0)
    assert none_counters == {}, "no scenario: no simulator"
    assert direct.ended is None and direct.latencies_ms, direct.summary()
    assert run.ended is None and len(run.latencies_ms) > 20, run.summary()
    assert relay_ports, "the answer named the simulator's ports"
    to_viewer = sum(c["to_operator"]["sent"] for c in counters.values())
    to_server = sum(c["to_robot"]["sent"] for c in counters.values())
    # at least a packet a frame reached the viewer through the simulator, and its RTCP and
    # DTLS/STUN came back through it too
    assert to_viewer >= len(run.latencies_ms) and to_server > 3, counters
    # the page greys a picture older than video_stale_ms: through metro (4 ms one way) the
    # median frame is far inside it, on any machine that can decode 15 fps at all
    stale_ms = DashboardConfig().video_stale_ms
    through = float(np.median(run.latencies_ms))
    assert through < stale_ms, f"p50 {through:.0f} ms through metro, stale after {stale_ms}"


def test_the_answer_names_only_the_simulator_and_the_offer_reaches_nobody_directly():
    from common.netsim.scenario import load_scenario
    from robot_side.video.simulated_link import SimulatedMediaPath, without_candidates

    offer = (
        "v=0\r\nm=video 9 UDP/TLS/RTP/SAVPF 97\r\n"
        "a=candidate:1 1 udp 2122260223 192.0.2.7 50000 typ host\r\n"
        "a=end-of-candidates\r\na=mid:0\r\n"
    )
    assert without_candidates(offer) == "v=0\r\nm=video 9 UDP/TLS/RTP/SAVPF 97\r\na=mid:0\r\n"
    answer = (
        "v=0\r\nm=video 40001 UDP/TLS/RTP/SAVPF 97\r\nc=IN IP4 127.0.0.1\r\n"
        "a=candidate:f 1 udp 2130706431 127.0.0.1 40001 typ host\r\na=end-of-candidates\r\n"
    )
    path = SimulatedMediaPath(load_scenario("metro"), seed=0, start_ns=0)
    try:
        routed = path.route(answer)
        (relay,) = path.relays.values()
        port = relay.address[1]
        assert relay.target == ("127.0.0.1", 40001)
        assert re.findall(r"127\.0\.0\.1 (\d+) typ host", routed) == [str(port)]
        assert f"m=video {port} " in routed and "40001" not in routed
    finally:
        path.stop()
