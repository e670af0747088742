"""The page's credential stays with its page and its port, in a real headless chromium.

A local web server on another port of 127.0.0.1, visited by the operator's
browser right after the dashboard (navigated to from the page itself, as a
link would), records every request it gets: it must see no cookie and the
token nowhere (path, query, Referer, any header). And a process that takes
the dashboard's port while the node restarts, as a squatter would, answers
the page's reconnects: what the page sends it must not hold the token.
"""

from __future__ import annotations

import asyncio
import http.server
import json
import threading

import pytest
from headless_chromium import Chromium, needs_chromium
from test_dashboard_server import FakeNode
from websockets.asyncio.server import serve

from operator_side.dashboard import Dashboard, DashboardConfig
from operator_side.dashboard.page_auth import CHALLENGE_PROTOCOL, challenge_mac

pytestmark = [pytest.mark.slow, pytest.mark.timeout(90), needs_chromium]


class RecordingServer(http.server.ThreadingHTTPServer):
    """Any local server the operator's browser may visit: it keeps what each request said."""

    def __init__(self) -> None:
        self.seen: list[tuple[str, dict[str, str]]] = []
        server = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                server.seen.append((self.path, dict(self.headers.items())))
                body = b"<html><body><img src='/pixel.png'>another local site</body></html>"
                self.send_response(200)
                self.send_header("Content-Type", "text/html")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, *args: object) -> None:
                pass

        super().__init__(("127.0.0.1", 0), Handler)
        self.port = self.server_address[1]
        threading.Thread(target=self.serve_forever, daemon=True).start()


def _page_is_live(browser: Chromium) -> None:
    browser.wait_until("dxp.connected && dxp.hello !== null", bool, timeout_s=20)


def test_another_local_port_the_browser_visits_receives_no_credential():
    node = FakeNode()
    other = RecordingServer()
    with Dashboard(node, DashboardConfig(port=0)) as d, Chromium() as browser:
        token = d.server.auth.token
        browser.navigate(d.url)
        _page_is_live(browser)
        # the token left the address bar at once, and nothing set a cookie
        assert token not in browser.evaluate("location.href")
        assert browser.evaluate("document.cookie") == ""
        # a reload: the bare address, the token from the tab's storage, the socket up again
        browser.navigate(d.server.base_url)
        _page_is_live(browser)
        # from the page, as a link or a script would take the browser elsewhere on 127.0.0.1
        browser.evaluate(f"location.href = 'http://127.0.0.1:{other.port}/from-the-page'")
        browser.wait_until(f"location.port === '{other.port}'", bool, timeout_s=10)
        browser.navigate(f"http://127.0.0.1:{other.port}/typed")  # and typed in
        browser.wait_until("document.readyState === 'complete'", bool, timeout_s=10)
    other.shutdown()
    paths = [path for path, _ in other.seen]
    assert "/from-the-page" in paths and "/typed" in paths, paths
    for path, headers in other.seen:
        assert "Cookie" not in headers, (path, headers)  # the old cookie reached every port
        assert token not in path, path
        for name, value in headers.items():
            assert token not in value, (path, name)


def test_a_process_on_the_dashboards_port_during_a_restart_learns_no_token_from_the_page():
    node = FakeNode()
    d = Dashboard(node, DashboardConfig(port=0))
    d.start()
    port, token = d.server.port, d.server.auth.token
    heard: list[str] = []  # the handshakes' headers and every message the page sent
    got_answer = threading.Event()

    async def squat(conn) -> None:
        heard.append(json.dumps(dict(conn.request.headers.raw_items())))
        await conn.send(json.dumps({"type": "auth_challenge", "nonce": "ab" * 16}))
        async for message in conn:
            heard.append(str(message))
            got_answer.set()

    async def squatter(stop: asyncio.Event) -> None:
        async with serve(
            squat,
            "127.0.0.1",
            port,
            select_subprotocol=lambda conn, offered: CHALLENGE_PROTOCOL,
        ):
            await stop.wait()

    with Chromium() as browser:
        browser.navigate(d.url)
        _page_is_live(browser)
        d.stop()  # the unit restarts: its port is free, and taken at once
        loop = asyncio.new_event_loop()
        stop = asyncio.Event()
        thread = threading.Thread(target=loop.run_until_complete, args=(squatter(stop),))
        thread.start()
        try:
            assert got_answer.wait(15), "the page never reconnected to the port"
        finally:
            loop.call_soon_threadsafe(stop.set)
            thread.join(10)
    assert heard
    for text in heard:
        assert token not in text, text
    # what it got is the answer to its own nonce only: worthless for any other challenge
    answers = [json.loads(t) for t in heard if t.startswith("{") and '"auth"' in t]
    assert answers and answers[0]["mac"] == challenge_mac(token, "ab" * 16)
