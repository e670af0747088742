"""The robot's bridge from link video signals to its video server, against the real server.

The offers are real WebRTC offers from an aiortc peer; the server is the real
``VideoServer`` on loopback. What a viewer sees is the signal the robot would
publish (``outgoing``) and whether the camera is open.
"""

from __future__ import annotations

import asyncio
import time

import pytest

pytest.importorskip("aiortc")

from common.wire.messages import VideoSignal
from common.wire.transport import CaptureLink
from robot_side.camera.config import TestPatternConfig
from robot_side.camera.test_pattern import TestPatternCamera
from robot_side.node import RobotNode
from robot_side.node.config import RenderConfig, RobotConfig, RobotLinkConfig
from robot_side.video.link_signalling import LinkSignalling
from robot_side.video.server import VideoConfig, VideoServer

pytestmark = [pytest.mark.timeout(60)]

ALICE, BOB = b"a" * 32, b"b" * 32


def _offer_sdp() -> str:
    async def make() -> str:
        from aiortc import RTCPeerConnection

        pc = RTCPeerConnection()
        pc.addTransceiver("video", direction="recvonly")
        await pc.setLocalDescription(await pc.createOffer())
        sdp = pc.localDescription.sdp
        await pc.close()
        return sdp

    return asyncio.run(make())


def _signal(kind: str, viewer: int, sdp: str | None = None) -> VideoSignal:
    return VideoSignal(seq=1, t_send_ns=1, kind=kind, viewer=viewer, sdp=sdp)


def _next(bridge: LinkSignalling, timeout_s: float = 15.0) -> VideoSignal:
    deadline = time.monotonic() + timeout_s
    while not bridge.outgoing:
        assert time.monotonic() < deadline, "the bridge said nothing"
        time.sleep(0.01)
    return bridge.outgoing.popleft()


def _until(cond, timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond() and time.monotonic() < deadline:
        time.sleep(0.02)


@pytest.fixture
def server():
    source = TestPatternCamera(TestPatternConfig(width=320, height=240, fps=15))
    with VideoServer(source, VideoConfig(port=0, max_viewers=1)) as s:
        yield s


@pytest.fixture
def bridge(server):
    b = LinkSignalling(server.url)
    yield b
    b.close()


def test_offer_is_answered_and_a_bye_from_someone_else_changes_nothing(server, bridge):
    bridge.on_signal(_signal("offer", 7, _offer_sdp()), ALICE)
    answer = _next(bridge)
    assert answer.kind == "answer" and answer.viewer == 7
    assert "m=video" in answer.sdp
    assert (answer.width, answer.height, answer.source) == (320, 240, "test_pattern")
    bridge.on_signal(_signal("bye", 7), BOB)  # not Bob's session to end
    time.sleep(0.3)
    assert bridge.sessions == 1 and server.viewing.viewers == 1
    bridge.on_signal(_signal("bye", 7), ALICE)
    _until(lambda: server.viewing.viewers == 0)
    assert server.viewing.viewers == 0 and bridge.sessions == 0


def test_a_viewer_beyond_the_servers_limit_is_told_why(server, bridge):
    bridge.on_signal(_signal("offer", 1, _offer_sdp()), ALICE)
    assert _next(bridge).kind == "answer"
    bridge.on_signal(_signal("offer", 2, _offer_sdp()), BOB)
    refused = _next(bridge)
    assert refused.kind == "closed" and refused.viewer == 2
    assert "at most 1 viewers" in refused.reason


def test_a_quiet_viewer_loses_its_session(server, bridge):
    bridge.on_signal(_signal("offer", 3, _offer_sdp()), ALICE)
    assert _next(bridge).kind == "answer"
    bridge.expire(lambda signer: signer != ALICE)
    closed = _next(bridge)
    assert closed.kind == "closed" and closed.reason == "the viewer went quiet"
    _until(lambda: server.viewing.viewers == 0)
    assert server.viewing.viewers == 0
    assert bridge.counters["video_sessions_expired"] == 1


def test_no_video_server_is_a_closed_session_with_the_address():
    # discard port: nothing listens, and nothing comes back within the wait
    bridge = LinkSignalling("ws://127.0.0.1:9/", server_wait_s=0.3)
    try:
        t0 = time.monotonic()
        bridge.on_signal(_signal("offer", 4, "v=0"), ALICE)
        closed = _next(bridge)
        assert closed.kind == "closed" and "ws://127.0.0.1:9/" in closed.reason
        assert "waited 0.3 s" in closed.reason and time.monotonic() - t0 >= 0.3
        assert bridge.counters["video_offers_waited"] == 1
    finally:
        if bridge is not None:
            bridge.close()


def test_a_robot_without_video_answers_an_offer_with_the_reason():
    link = CaptureLink()
    config = RobotConfig(render=RenderConfig(mode="direct"), link=RobotLinkConfig())
    node = RobotNode(config, None, link=link)
    offer = _signal("offer", 5, "v=0")
    offer.session, offer.echo_session = 7, node.session  # an operator run that heard this one
    link.deliver(offer, 1)
    node.receive(1)
    sent = [m for m in link.messages if isinstance(m, VideoSignal)]
    assert len(sent) == 1 and sent[0].kind == "closed" and sent[0].viewer == 5
    assert "link.video_url" in sent[0].reason


@pytest.mark.slow
def test_a_video_server_that_died_and_came_back_serves_the_next_offer(tmp_path):
    """kill -9 of the video server: the session it held ends with "closed"; an offer while it
    is down waits for it and is answered once it is back on its port, without the viewer
    offering again (the token is read from the server's token file again: the restarted
    server has it)."""
    from tests_support import VideoServerProcess

    token_file = tmp_path / "video.token"
    settings = ("test_pattern.width=320", "test_pattern.height=240", "test_pattern.fps=15")
    settings += (f'token_file="{token_file}"',)
    first = VideoServerProcess(None, *settings)  # on a port of its own: said when ready
    bridge = None
    try:
        with first:
            # waits as long as the restarted server may take on a busy machine (the product's
            # SERVER_WAIT_S bounds it within the dashboard's wait for the answer)
            bridge = LinkSignalling(
                f"ws://127.0.0.1:{first.port}/", token_file=token_file, server_wait_s=60.0
            )
            bridge.on_signal(_signal("offer", 1, _offer_sdp()), ALICE)
            assert _next(bridge).kind == "answer"
            first.proc.kill()  # SIGKILL: no close frame, no goodbye
            ended = _next(bridge)
        assert ended.kind == "closed" and ended.viewer == 1
        assert "stopped" in ended.reason, ended.reason
        bridge.on_signal(_signal("offer", 2, _offer_sdp()), ALICE)  # while it is down
        time.sleep(0.5)
        assert not bridge.outgoing, bridge.outgoing  # not refused: waiting for the server
        with VideoServerProcess(first.port, *settings):  # back, on the same port
            again = _next(bridge, timeout_s=60.0)
            assert again.kind == "answer" and again.viewer == 2, again
        assert bridge.counters["video_offers_waited"] == 1
    finally:
        if bridge is not None:
            bridge.close()
