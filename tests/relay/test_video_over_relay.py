"""Video through the relay: signalling rides the nodes' links, so no site opens a port.

Real processes: a relay, a robot node in relay mode with a video server on its
own machine's loopback, and an observer's operator node with its dashboard.
The test is the observer's browser: aiortc speaks the page's protocol to the
dashboard's WebSocket, gets the robot's answer through the relay, and
decodes the stamped test pattern. Closing the page stops the camera, read
from the video server's own log.
"""

from __future__ import annotations

import asyncio
import json
import time

import pytest

pytest.importorskip("aiortc")

from common.transport import free_loopback_ports
from deploy.fleet import Fleet
from robot_side.video.stamp import read_stamp

pytestmark = [pytest.mark.slow, pytest.mark.timeout(120)]


async def _watch(page_ws: str, frames: int) -> dict:
    """The page's side: offer over the dashboard's socket, then decode ``frames`` frames."""
    from aiortc import RTCPeerConnection, RTCSessionDescription
    from websockets.asyncio.client import connect

    pc = RTCPeerConnection()
    pc.addTransceiver("video", direction="recvonly")
    track_future: asyncio.Future = asyncio.get_running_loop().create_future()
    pc.on("track", lambda track: track_future.done() or track_future.set_result(track))
    await pc.setLocalDescription(await pc.createOffer())
    stamps = []
    try:
        async with connect(page_ws, max_size=2**22) as ws:
            await ws.send(json.dumps({"type": "video_offer", "sdp": pc.localDescription.sdp}))
            while True:
                msg = json.loads(await asyncio.wait_for(ws.recv(), 20))
                if msg["type"] in ("video_answer", "video_closed"):
                    break
            if msg["type"] == "video_closed":
                return {"closed": msg["reason"]}
            await pc.setRemoteDescription(RTCSessionDescription(msg["sdp"], "answer"))
            track = await asyncio.wait_for(track_future, 20)
            for _ in range(frames):
                frame = await asyncio.wait_for(track.recv(), 20)
                stamp = read_stamp(frame.to_ndarray(format="rgb24"))
                if stamp is not None:
                    stamps.append(stamp)
        return {"answer": msg, "stamps": stamps}
    finally:
        await pc.close()


def test_an_observer_watches_through_the_relay_and_the_camera_stops_when_it_leaves(
    tmp_path, quiet_gc
):
    fleet = Fleet(robots=["cell1"], operators={"obs1": "observer"}, workdir=tmp_path)
    page_port = free_loopback_ports(1)[0]
    with fleet:
        fleet.start_relay()
        video, video_url = fleet.start_video()
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
        out = asyncio.run(_watch(f"ws://127.0.0.1:{page_port}/ws", frames=30))
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
