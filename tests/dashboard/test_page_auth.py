"""Who may open the dashboard: a local client without the run's token gets nothing, and a
request under another host name (DNS rebinding) is refused even with it.

Each client here is what another process on the operator's machine could
be: plain HTTP and WebSocket clients on real sockets. What they got is read
from their own responses, and what reached the node from its recorded
commands.
"""

from __future__ import annotations

import http.client
import json
import socket

import pytest
from test_dashboard_server import FakeNode, _next
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect

from common.errors import ConfigError
from common.web.web_token import from_query, with_token
from operator_side.dashboard import Dashboard, DashboardConfig
from operator_side.dashboard.config import TOKEN_ENV
from operator_side.dashboard.page_auth import CHALLENGE_PROTOCOL, PageAuth, challenge_mac
from operator_side.dashboard.web import AUTH_TIMEOUT_S, CLOSE_UNAUTHORIZED

pytestmark = pytest.mark.timeout(30)

CLOSE = json.dumps({"type": "command", "action": "gripper_close", "grip_level": 31})


@pytest.fixture
def dashboard():
    node = FakeNode()
    d = Dashboard(node, DashboardConfig(port=0, allowed_hosts=["operator.vpn"]))
    d.start()
    try:
        yield node, d
    finally:
        d.stop()


def get(d: Dashboard, target: str, **headers: str) -> http.client.HTTPResponse:
    conn = http.client.HTTPConnection("127.0.0.1", d.server.port, timeout=2)
    conn.request("GET", target, headers=headers)
    response = conn.getresponse()
    response.read()
    conn.close()
    return response


def refused(url: str, status: int, **kw) -> None:
    """Opening the WebSocket at ``url`` fails with ``status``: no socket, no state, no hello."""
    with pytest.raises(InvalidStatus) as e, connect(url, open_timeout=2, **kw):
        pass
    assert e.value.response.status_code == status


def challenged(url: str, reply: object | None, **kw) -> tuple[int, list[dict]]:
    """A page's socket answering the server's challenge with ``reply`` (None: nothing): the
    close code it got and every message it was sent besides the challenge."""
    with connect(url, subprotocols=[CHALLENGE_PROTOCOL], open_timeout=2, **kw) as ws:
        challenge = json.loads(ws.recv(timeout=2))
        assert challenge["type"] == "auth_challenge" and len(challenge["nonce"]) >= 32
        got = []
        with pytest.raises(ConnectionClosed) as e:
            if reply is not None:
                ws.send(json.dumps(reply(challenge["nonce"]) if callable(reply) else reply))
            # a command before (or instead of) a right answer; after a wrong one the server
            # may have closed already (a busy client sends it late): refused either way
            ws.send(CLOSE)
            while True:
                got.append(json.loads(ws.recv(timeout=AUTH_TIMEOUT_S + 2)))
    return e.value.rcvd.code, got


def test_without_the_token_no_socket_opens_and_no_command_gets_through(dashboard):
    node, d = dashboard
    token = d.server.auth.token
    bare_ws = f"ws://127.0.0.1:{d.server.port}/ws"
    # a wrong token, for a file or the socket: 401
    for target in ("/?token=guess", "/app.js?token=guess", "/ws?token=guess"):
        assert get(d, target).status == 401, target
    assert get(d, "/", Authorization="Bearer guess").status == 401
    # a socket with no token and no challenge: 401 before the upgrade
    refused(bare_ws, 401)
    refused(with_token(bare_ws, "x" * 32), 401)
    refused(bare_ws, 401, additional_headers={"Authorization": "Bearer guess"})
    # the challenge answered wrongly, with the token of another run, or not at all: closed
    wrong = {"type": "auth", "mac": challenge_mac("x" * 32, "0" * 32)}
    for reply in (
        wrong,
        lambda nonce: {"type": "auth", "mac": challenge_mac("another-run-token-0123", nonce)},
        {"type": "auth", "token": "guess"},
        None,
    ):
        code, got = challenged(bare_ws, reply)
        assert code == CLOSE_UNAUTHORIZED and got == [], (reply, got)
    assert node.commands == []
    # with the token the same clients are served: the refusals above were the token's
    assert get(d, "/app.js", Authorization=f"Bearer {token}").status == 200
    with connect(d.ws_url) as ws:
        assert _next(ws, "hello")
        ws.send(CLOSE)
        assert _next(ws, "ack")["ok"] is True
    with connect(bare_ws, subprotocols=[CHALLENGE_PROTOCOL]) as ws:
        nonce = json.loads(ws.recv(timeout=2))["nonce"]
        ws.send(json.dumps({"type": "auth", "mac": challenge_mac(token, nonce)}))
        assert _next(ws, "hello")
        ws.send(CLOSE)
        assert _next(ws, "ack")["ok"] is True
    assert node.commands == [("gripper_close", 31)] * 2


def test_the_page_is_served_without_a_cookie_and_its_files_carry_nothing_of_the_run(dashboard):
    _, d = dashboard
    token = d.server.auth.token
    first = get(d, "/" + d.url.split("/", 3)[3])  # the printed URL
    assert first.status == 200
    assert first.getheader("Set-Cookie") is None  # no cookie: it would reach every port
    assert first.getheader("Referrer-Policy") == "no-referrer"
    # a reload (the token gone from the address bar): the page's own files, none holding it
    for target in ("/", "/app.js", "/patterns.js", "/style.css"):
        conn = http.client.HTTPConnection("127.0.0.1", d.server.port, timeout=2)
        conn.request("GET", target)
        response = conn.getresponse()
        body = response.read()
        conn.close()
        assert response.status == 200 and response.getheader("Set-Cookie") is None, target
        assert token.encode() not in body, target


def test_a_request_under_a_rebinding_name_is_refused_even_with_the_token(dashboard):
    node, d = dashboard
    port, token = d.server.port, d.server.auth.token
    for name in ("evil.example", "127.0.0.1.evil.example", "localhost.evil.example"):
        host = f"{name}:{port}"
        origin = f"http://{host}"
        assert get(d, f"/?token={token}", Host=host, Origin=origin).status == 403
        assert get(d, "/app.js", Host=host, Authorization=f"Bearer {token}").status == 403
        # the page's WebSocket as a rebound page opens it: its own name, its own origin
        sock = socket.create_connection(("127.0.0.1", port), timeout=2)
        url = with_token(f"ws://{host}/ws", token)
        with pytest.raises(InvalidStatus) as e, connect(url, sock=sock, origin=origin):
            pass
        assert e.value.response.status_code == 403
    # a repeated Host cannot smuggle one past the check
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=2)
    conn.putrequest("GET", f"/?token={token}", skip_host=True)
    conn.putheader("Host", f"127.0.0.1:{port}")
    conn.putheader("Host", f"evil.example:{port}")
    conn.endheaders()
    assert conn.getresponse().status == 400
    conn.close()
    # a name in dashboard.allowed_hosts is served, and so is localhost
    for name in ("operator.vpn", "localhost", "LOCALHOST"):
        host = f"{name}:{port}"
        sock = socket.create_connection(("127.0.0.1", port), timeout=2)
        with connect(
            with_token(f"ws://{host}/ws", token), sock=sock, origin=f"http://{host}"
        ) as ws:
            assert _next(ws, "hello")
            ws.send(CLOSE)
            assert _next(ws, "ack")["ok"] is True
    assert len(node.commands) == 3


def test_a_matching_origin_of_another_host_and_a_foreign_origin_are_refused(dashboard):
    _, d = dashboard
    port = d.server.port
    refused(d.ws_url, 403, origin="http://evil.example")
    refused(d.ws_url, 403, origin=f"http://localhost:{port}")  # the Host is 127.0.0.1
    refused(d.ws_url, 403, origin="null")
    with connect(d.ws_url, origin=f"http://127.0.0.1:{port}") as ws:
        assert _next(ws, "hello")


def test_the_token_comes_from_the_config_or_the_environment_else_it_is_fresh(monkeypatch):
    node = FakeNode()
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    fresh = [Dashboard(node, DashboardConfig(port=0)).server.auth.token for _ in range(2)]
    assert fresh[0] != fresh[1] and len(fresh[0]) >= 32
    fixed = "a-scripted-setup-token-0123"
    d = Dashboard(node, DashboardConfig(port=0, token=fixed))
    assert from_query(d.url) == fixed
    monkeypatch.setenv(TOKEN_ENV, "from-the-environment-0123")
    assert Dashboard(node, DashboardConfig(port=0)).server.auth.token.startswith("from-the-env")
    assert Dashboard(node, DashboardConfig(port=0, token=fixed)).server.auth.token == fixed
    with pytest.raises(ConfigError, match="at least 16"):
        DashboardConfig(token="short")
    monkeypatch.setenv(TOKEN_ENV, "short")
    with pytest.raises(ConfigError, match=TOKEN_ENV):
        Dashboard(node, DashboardConfig(port=0))


def test_a_wildcard_bind_accepts_the_machines_addresses_but_names_only_from_the_allowlist():
    auth = PageAuth(allowed_hosts=["ops.lab.example"])
    auth.bind("0.0.0.0", 8765)
    for host in ("192.168.1.20:8765", "[fe80::1]:8765", "127.0.0.1", "ops.lab.example:8765"):
        assert auth.host_allowed(host), host
    for host in ("evil.example:8765", "192.168.1.20.evil.example", "", ":8765"):
        assert not auth.host_allowed(host), host
    bound = PageAuth()
    bound.bind("10.0.0.5", 8765)
    assert bound.host_allowed("10.0.0.5:8765") and not bound.host_allowed("10.0.0.6:8765")
