"""A small local web server: static files over HTTP and one WebSocket, on one port.

Both the dashboard and the perception study's answer page use it. One port
serves everything, so a remote operator needs a single SSH tunnel. The
asyncio loop runs on its own thread: the node's 60 Hz loop never waits for a
browser, and a slow browser never holds up anything but its own updates.

Pages come only from files in the package (no CDN, nothing external), and a
Content-Security-Policy header tells the browser to load nothing from
anywhere else either. Every request must name an allowed host, and the
WebSocket must prove the run's token, in its request (scripts) or by the
page's answer to a challenge before anything else is sent or read
(``page_auth.py``); ``url`` is the address to open, with the token in it.
"""

from __future__ import annotations

import asyncio
import http
import json
import logging
import secrets
import threading
import weakref
from collections.abc import Awaitable, Callable, Iterable, Mapping
from dataclasses import dataclass
from importlib import resources
from typing import Any
from urllib.parse import urlsplit

from websockets.asyncio.server import ServerConnection, broadcast, serve
from websockets.datastructures import Headers
from websockets.http11 import Request, Response

from common.errors import ConfigError
from common.web import web_token
from operator_side.dashboard.page_auth import CHALLENGE_PROTOCOL, PageAuth, Refusal

log = logging.getLogger(__name__)
# websockets logs every HTTP request at INFO; a page load is five of them.
# Quiet by default; set this logger to INFO to see them.
_wire_log = logging.getLogger(__name__ + ".wire")
_wire_log.setLevel(logging.WARNING)

CONTENT_TYPES = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".css": "text/css; charset=utf-8",
    ".png": "image/png",
    ".json": "application/json",
}
# Same-origin only: the page may talk to its own server and nothing else.
CSP = (
    "default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data:; "
    "connect-src 'self'; object-src 'none'; base-uri 'none'; frame-ancestors 'none'"
)
# A client whose unsent data passes this is skipped until it catches up:
# the newest state matters, a backlog of old ones does not.
MAX_BUFFERED_BYTES = 256 * 1024
#: a page's socket must answer the token challenge within this, or it is closed
AUTH_TIMEOUT_S = 5.0
#: the close code of a socket that did not prove the token (the page says so)
CLOSE_UNAUTHORIZED = 4401


@dataclass(frozen=True)
class StaticFile:
    body: bytes
    content_type: str


def package_files(package: str, names: Iterable[str]) -> dict[str, StaticFile]:
    """``/name`` -> file, read once from the installed package (wheel or editable)."""
    root = resources.files(package)
    out = {}
    for name in names:
        suffix = name[name.rfind(".") :]
        out[f"/{name}"] = StaticFile(
            (root / name).read_bytes(), CONTENT_TYPES.get(suffix, "application/octet-stream")
        )
    return out


Handler = Callable[[ServerConnection], Awaitable[None]]


class WebServer:
    """Serves ``files`` at their paths (``/`` is ``/index.html``) and ``handler`` at ``/ws``.

    ``background`` coroutines run on the server's loop for as long as it is
    up (the dashboard's sampler). ``start`` returns once the port is bound,
    or raises ``ConfigError`` naming the address when it cannot be.
    """

    def __init__(
        self,
        host: str,
        port: int,
        files: Mapping[str, StaticFile],
        handler: Handler,
        *,
        name: str = "web",
        background: Iterable[Callable[[], Awaitable[None]]] = (),
        ws_path: str = "/ws",
        auth: PageAuth | None = None,
    ) -> None:
        self.host = host
        self.port = port
        self.files = dict(files)
        if "/index.html" in self.files:
            self.files.setdefault("/", self.files["/index.html"])
        self.handler = handler
        self.name = name
        self.background = list(background)
        self.ws_path = ws_path
        self.auth = auth or PageAuth(name=name)
        self.loop: asyncio.AbstractEventLoop | None = None
        self.connections: set[ServerConnection] = set()
        self._thread: threading.Thread | None = None
        self._started = threading.Event()
        self._stop: asyncio.Event | None = None
        self._error: BaseException | None = None
        #: sockets whose request carried the token (scripts): no challenge
        self._proven: weakref.WeakSet[ServerConnection] = weakref.WeakSet()
        self.auth_refused = 0  # sockets closed for a missing or wrong answer to the challenge

    @property
    def base_url(self) -> str:
        """The server's address without the token: what a log line may show."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        if host in ("0.0.0.0", "[::]", ""):
            host = "127.0.0.1"
        return f"http://{host}:{self.port}/"

    @property
    def url(self) -> str:
        """The address to open in a browser: it carries the token (keep it to yourself)."""
        return web_token.with_token(self.base_url, self.auth.token)

    @property
    def ws_url(self) -> str:
        """The WebSocket's address, token included (what a script connects to)."""
        ws = self.base_url.replace("http://", "ws://", 1) + self.ws_path.lstrip("/")
        return web_token.with_token(ws, self.auth.token)

    def start(self, timeout_s: float = 5.0) -> None:
        if self._thread is not None:
            raise RuntimeError(f"{self.name} server already started")
        self._thread = threading.Thread(target=self._run, name=f"{self.name}-server", daemon=True)
        self._thread.start()
        if not self._started.wait(timeout_s):
            raise ConfigError(f"{self.name} server did not start within {timeout_s} s")
        if self._error is not None:
            self._thread.join(timeout_s)
            self._thread = None
            raise ConfigError(
                f"{self.name}: cannot serve on {self.host}:{self.port}: {self._error} "
                "(is another program using the port? choose another one)"
            ) from None
        log.info("%s server at %s (token-protected)", self.name, self.base_url)

    def stop(self, timeout_s: float = 5.0) -> None:
        thread, self._thread = self._thread, None
        if thread is None:
            return
        if self.loop is not None and self._stop is not None:
            self.loop.call_soon_threadsafe(self._stop.set)
        thread.join(timeout_s)
        if thread.is_alive():
            log.warning("%s server did not stop within %s s", self.name, timeout_s)

    def call(self, fn: Callable[..., Any], *args: Any) -> None:
        """Run ``fn(*args)`` on the server's loop, from any thread."""
        if self.loop is not None:
            self.loop.call_soon_threadsafe(fn, *args)

    # ------------------------------------------------------------ internals
    def _run(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as e:  # reported to start(), or logged
            if not self._started.is_set():
                self._error = e
                self._started.set()
            else:
                log.exception("%s server stopped on an error", self.name)

    async def _main(self) -> None:
        self.loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        async with serve(
            self._serve_ws,
            self.host,
            self.port,
            process_request=self._process_request,
            select_subprotocol=_select_subprotocol,
            compression=None,  # small JSON at up to 60 Hz: deflate costs more CPU than it saves
            max_size=64 * 1024,  # pages send only tiny commands
            ping_interval=10,
            ping_timeout=10,
            # after a page or a refusal, a client that keeps its socket open
            # must not hold up stop() for the default 10 s
            close_timeout=1,
            logger=_wire_log,
        ) as server:
            self.port = server.sockets[0].getsockname()[1]
            self.auth.bind(self.host, self.port)
            tasks = [asyncio.create_task(fn()) for fn in self.background]
            self._started.set()
            try:
                await self._stop.wait()
            finally:
                for t in tasks:
                    t.cancel()
                await asyncio.gather(*tasks, return_exceptions=True)
                for conn in list(self.connections):
                    await conn.close(1001, "server stopping")

    async def _serve_ws(self, conn: ServerConnection) -> None:
        if conn not in self._proven and not await self._challenge(conn):
            self.auth_refused += 1
            await conn.close(CLOSE_UNAUTHORIZED, "the page's token is needed")
            return
        self.connections.add(conn)
        try:
            await self.handler(conn)
        finally:
            self.connections.discard(conn)

    async def _challenge(self, conn: ServerConnection) -> bool:
        """The page proves the token without sending it: a fresh nonce, its HMAC back."""
        nonce = secrets.token_hex(16)
        try:
            await conn.send(json.dumps({"type": "auth_challenge", "nonce": nonce}))
            raw = await asyncio.wait_for(conn.recv(), AUTH_TIMEOUT_S)
            reply = json.loads(raw)
        except (TimeoutError, ValueError, TypeError, RecursionError):
            reply = None
        except Exception:  # the peer went away: nothing to prove, nothing to serve
            return False
        if self.auth.answers(nonce, reply):
            return True
        log.info("%s: closed a socket that did not prove the token", self.name)
        return False

    def _process_request(self, conn: ServerConnection, request: Request) -> Response | None:
        path = urlsplit(request.path).path
        headers = _single_headers(request.headers)
        if headers is None:
            return _response(http.HTTPStatus.BAD_REQUEST, b"repeated header\n", "text/plain")
        # A browser always sends Origin on a WebSocket; one from another site is a
        # page trying to drive the gripper through the operator's browser.
        refusal = self.auth.check(request.path, headers, websocket=path == self.ws_path)
        if refusal is not None:
            return _refusal(refusal)
        if path == self.ws_path:
            if self.auth.proven(request.path, headers):
                self._proven.add(conn)
            return None
        static = self.files.get(path)
        if static is None:
            return _response(http.HTTPStatus.NOT_FOUND, b"not found\n", "text/plain")
        return _response(http.HTTPStatus.OK, static.body, static.content_type)

    def send(self, conn: ServerConnection, message: str) -> bool:
        """Queue ``message`` for one client unless it lags; False when skipped.

        Never waits (call it on the server's loop): it only appends to the
        connection's buffer, and a client already holding a backlog is skipped.
        """
        transport = getattr(conn, "transport", None)
        if transport is not None and transport.get_write_buffer_size() > MAX_BUFFERED_BYTES:
            return False
        broadcast([conn], message)
        return True


AUTH_HEADERS = ("Host", "Origin", "Authorization", "Sec-WebSocket-Protocol")


def _select_subprotocol(conn: ServerConnection, offered: Any) -> Any:
    """The challenge's subprotocol when the page offers it (the browser requires an answer
    naming one it offered); none otherwise."""
    return CHALLENGE_PROTOCOL if CHALLENGE_PROTOCOL in offered else None


def _single_headers(headers: Headers) -> dict[str, str] | None:
    """The headers the page's checks read; None when one is repeated (which one would count?)."""
    out = {}
    for name in AUTH_HEADERS:
        values = headers.get_all(name)
        if len(values) > 1:
            return None
        if values:
            out[name] = values[0]
    return out


def _refusal(refusal: Refusal) -> Response:
    response = _response(refusal.status, refusal.body, "text/plain; charset=utf-8")
    for name, value in refusal.headers:
        response.headers[name] = value
    return response


def _response(status: http.HTTPStatus, body: bytes, content_type: str) -> Response:
    headers = Headers(
        [
            ("Content-Type", content_type),
            ("Content-Length", str(len(body))),
            ("Cache-Control", "no-store"),
            ("X-Content-Type-Options", "nosniff"),
            ("Content-Security-Policy", CSP),
            ("Referrer-Policy", "no-referrer"),  # the first URL carries the token
            ("Connection", "close"),
        ]
    )
    return Response(status.value, status.phrase, headers, body)
