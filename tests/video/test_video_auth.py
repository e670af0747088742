"""The video server's signalling, from another process: without its token nobody gets an
answer (so no peer connection, no picture), and a browser page is refused outright."""

from __future__ import annotations

import json

import pytest

pytest.importorskip("aiortc")

from test_link_signalling import ALICE, _next, _offer_sdp, _signal
from tests_support import VideoServerProcess
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from common.web.web_token import with_token, without_token
from robot_side.video.link_signalling import LinkSignalling

pytestmark = [pytest.mark.slow, pytest.mark.timeout(60)]


def test_without_the_token_no_answer_and_the_camera_stays_closed(tmp_path):
    token_file = tmp_path / "video.token"
    settings = ("test_pattern.width=160", "test_pattern.height=120", f'token_file="{token_file}"')
    with VideoServerProcess(None, *settings) as server:
        bare = f"ws://127.0.0.1:{server.port}/"
        assert without_token(server.url) == bare  # printed without the token: it is in the file
        token = token_file.read_text().strip()
        assert token_file.stat().st_mode & 0o777 == 0o600
        offer = json.dumps({"type": "offer", "sdp": _offer_sdp()})
        for url, kw, status in (
            (bare, {}, 401),
            (with_token(bare, "x" * 32), {}, 401),
            (bare, {"additional_headers": {"Authorization": "Bearer guess"}}, 401),
            (with_token(bare, token), {"origin": f"http://127.0.0.1:{server.port}"}, 403),
        ):
            with pytest.raises(InvalidStatus) as e, connect(url, open_timeout=5, **kw) as ws:
                ws.send(offer)
            assert e.value.response.status_code == status, url
        # the robot's bridge with a wrong token file is told why, and gets no answer
        wrong = tmp_path / "other.token"
        bridge = LinkSignalling(bare, token_file=wrong)
        try:
            bridge.on_signal(_signal("offer", 1, _offer_sdp()), ALICE)
            closed = _next(bridge)
            assert closed.kind == "closed" and "video_token_file" in closed.reason
            assert token not in closed.reason
        finally:
            bridge.close()
        # with the token (the same bridge reading the server's file) the offer is answered
        bridge = LinkSignalling(bare, token_file=token_file)
        try:
            bridge.on_signal(_signal("offer", 2, _offer_sdp()), ALICE)
            assert _next(bridge).kind == "answer"
        finally:
            bridge.close()
    log = server.log_text()
    assert log.count("video: refused a signalling request") == 5, log[-2000:]
    assert token not in log
