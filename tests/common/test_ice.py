"""ICE servers: both ends of a video call get the same list, and none by default."""

from __future__ import annotations

import json
import time

import pytest
from websockets.sync.client import connect

from common.errors import ConfigError
from common.wire.ice import IceConfig
from operator_side.dashboard import Dashboard, DashboardConfig


def test_default_is_host_candidates_only():
    assert IceConfig().as_dicts() == []


def test_turn_needs_credentials_and_the_password_is_read_from_its_file(tmp_path):
    with pytest.raises(ValueError, match="TURN server needs"):
        IceConfig(servers=("turn:relay.example.org:3478",))
    with pytest.raises(ValueError, match="must start with"):
        IceConfig(servers=("relay.example.org:3478",))
    secret = tmp_path / "turn.secret"
    secret.write_text("s3cret\n")
    ice = IceConfig(
        servers=("stun:relay.example.org:3478", "turn:relay.example.org:3478"),
        username="cell1",
        credential_file=secret,
    )
    assert ice.as_dicts() == [
        {
            "urls": ["stun:relay.example.org:3478", "turn:relay.example.org:3478"],
            "username": "cell1",
            "credential": "s3cret",
        }
    ]
    missing = IceConfig(servers=("turn:x:3478",), username="u", credential_file=tmp_path / "nope")
    with pytest.raises(ConfigError, match="nope"):
        missing.as_dicts()


def test_the_robots_video_server_asks_no_stun_server_unless_told():
    pytest.importorskip("aiortc")
    from robot_side.video.server import rtc_configuration

    assert rtc_configuration(IceConfig()).iceServers == []  # aiortc alone would ask Google's
    servers = rtc_configuration(IceConfig(servers=("stun:10.0.0.1:3478",))).iceServers
    assert [s.urls for s in servers] == [["stun:10.0.0.1:3478"]]


class _Node:
    def snapshot(self):  # the page's first state never arrives: only the hello is read
        raise RuntimeError("not needed")

    def send_command(self, *args, **kwargs) -> None:
        pass


def test_the_page_is_told_the_dashboards_ice_servers():
    ice = IceConfig(servers=("stun:10.0.0.1:3478",))
    config = DashboardConfig(port=0, video_url="ws://127.0.0.1:9/", ice=ice)
    d = Dashboard(_Node(), config)
    d.start()
    try:
        with connect(d.ws_url) as ws:
            deadline = time.monotonic() + 5
            while True:
                msg = json.loads(ws.recv(timeout=max(0.01, deadline - time.monotonic())))
                if msg["type"] == "hello":
                    break
        assert msg["video"] is True
        assert msg["ice_servers"] == [{"urls": ["stun:10.0.0.1:3478"]}]
        assert msg["ice_transport_policy"] == "all"
    finally:
        d.stop()


def test_relay_only_needs_a_turn_server_and_is_the_only_other_policy(tmp_path):
    with pytest.raises(ValueError, match="needs a TURN server"):
        IceConfig(servers=("stun:10.0.0.1:3478",), transport_policy="relay")
    with pytest.raises(ValueError, match="'all' or 'relay'"):
        IceConfig(transport_policy="direct")
    secret = tmp_path / "pw"
    secret.write_text("x")
    turn = IceConfig(
        servers=("turn:10.0.0.1:3478",),
        username="u",
        credential_file=secret,
        transport_policy="relay",
    )
    assert turn.as_dicts()[0]["credential"] == "x"
