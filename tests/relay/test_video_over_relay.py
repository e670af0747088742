"""Video through the relay or the fabric's router: signalling rides the nodes' links, so no
site opens a port.

Real processes: a relay (or a router), a robot node in relay (or fabric) mode
with a video server on its own machine's loopback, and an observer's operator
node with its dashboard.
The test is the observer's browser: aiortc speaks the page's protocol to the
dashboard's WebSocket, gets the robot's answer through the relay, and
decodes the stamped test pattern. Closing the page stops the camera, read
from the video server's own log.
"""

from __future__ import annotations

import asyncio
import re
import time

import pytest

pytest.importorskip("aiortc")

from video_page import watch_video

from common.transport import free_loopback_ports
from common.web_token import from_query, with_token
from harness.fleet import Fleet

pytestmark = [pytest.mark.slow, pytest.mark.timeout(120), pytest.mark.parallel]


@pytest.mark.parametrize("transport", ["relay", "fabric"])
def test_an_observer_watches_through_the_relay_and_the_camera_stops_when_it_leaves(
    tmp_path, quiet_gc, transport
):
    # video is a controller's: this observer's roster entry grants it (video = true)
    fleet = Fleet(
        robots=["cell1"],
        operators={"obs1": "observer"},
        workdir=tmp_path,
        video_observers=frozenset({"obs1"}),
        transport=transport,
    )
    page_port = free_loopback_ports(1)[0]
    with fleet:
        hub = fleet.start_hub()
        if transport == "fabric":
            fleet.wait_for(lambda: "router up" in hub.log_text(), 30, "the router")
        video, video_url = fleet.start_video()
        # up before the first offer: an offer to a server not yet listening is answered
        # "closed" (the robot tells a viewer the camera is not there, it does not wait)
        serving = lambda: "video signalling at" in video.log_text()  # noqa: E731
        fleet.wait_for(serving, 30, "the video server")
        fleet.start_robot("cell1", None, video_url=video_url)
        dashboard = [
            "--set",
            "operator.dashboard.enabled=true",
            "--set",
            f"operator.dashboard.port={page_port}",
            "--set",
            'operator.dashboard.video_url="link"',
        ]
        fleet.start_operator("obs1", "cell1", want_frames=False, extra=dashboard)
        operator_log = fleet.procs["obs1@cell1"].log_text
        fleet.wait_for(lambda: "operator node up" in operator_log(), 30, "the operator node")
        time.sleep(1.0)  # the subscriptions cross the relay
        # the page's URL as the node printed it, with its token
        token = from_query(re.search(r"dashboard: (\S+)", operator_log())[1])
        page_ws = with_token(f"ws://127.0.0.1:{page_port}/ws", token)
        out = asyncio.run(watch_video(page_ws, frames=30))
        assert "closed" not in out, out
        answer = out["answer"]
        assert (answer["width"], answer["height"]) == (320, 240)
        assert answer["source"] == "test_pattern"
        # The stamped pattern survived VP8: these are the robot's camera frames.
        assert len(out["stamps"]) >= 20, out["stamps"]
        counters = [c for _, c in out["stamps"]]
        assert len(set(counters)) >= 15
        # The page left: the dashboard said bye through the relay and the camera closed.
        closed = lambda: "closed (no viewers)" in video.log_text()  # noqa: E731
        fleet.wait_for(closed, 15, "the video source to close")
        assert "opened for a viewer" in video.log_text()
        fleet.stop("obs1@cell1")
        fleet.stop("cell1")
    robot = fleet.procs["cell1"].stats()
    assert robot.get("video_answers_sent") == 1, robot
    assert robot.get("video_offers") == 1, robot
