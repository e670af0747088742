"""Who may open a page: the run's token, and only under a name this machine answers to.

The token is the page's alone, bound to its origin (scheme, host and port):
no cookie, which a browser would send to every port of 127.0.0.1 (any local
server the operator's browser visits would receive it). The printed URL
carries it as ``?token=``; the page's script keeps it in ``sessionStorage``
(per origin and per tab), takes it out of the address bar, and proves it on
its WebSocket without sending it: the server sends a fresh nonce, the page
answers ``HMAC-SHA256(token, "deepxpalm-page:" + nonce)`` (``challenge_mac``).
A process squatting the port while the node restarts then learns nothing
from the page's reconnects. Scripts send ``Authorization: Bearer <token>``
(or ``?token=``) instead.

The page's files themselves (HTML, script, style: the package's, nothing of
the run) are served without the token, so a reload (whose URL no longer has
it) loads the page, which then authenticates its socket from the tab's
storage. A token that is given and wrong is refused (401), and a WebSocket
with neither a token nor the challenge's subprotocol gets 401 before the
upgrade.

The ``Host`` header must name this server: the address it is bound to,
``127.0.0.1``, ``localhost``, ``[::1]``, or a name in the allowlist. That
stops DNS rebinding, where a site's name is made to resolve to 127.0.0.1 so
that its page becomes same-origin with ours: the browser then sends
``Host: evil.example``. An ``Origin`` (browsers send one on every WebSocket)
must be this same host. An IP literal cannot be rebound, so on a wildcard
bind (0.0.0.0) any address of the machine is accepted; names still need the
allowlist.
"""

from __future__ import annotations

import hashlib
import hmac
import http
import ipaddress
import logging
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from urllib.parse import urlsplit

from common.web import web_token

log = logging.getLogger(__name__)

LOCAL_NAMES = ("127.0.0.1", "localhost", "::1")
WILDCARDS = ("", "0.0.0.0", "::")


#: the WebSocket subprotocol a page offers to authenticate by challenge (no token in the request)
CHALLENGE_PROTOCOL = "deepxpalm.challenge"
CHALLENGE_CONTEXT = "deepxpalm-page:"


def challenge_mac(token: str, nonce: str) -> str:
    """What a page holding ``token`` answers to ``nonce``: HMAC-SHA256, hex."""
    return hmac.new(
        token.encode(), (CHALLENGE_CONTEXT + nonce).encode(), hashlib.sha256
    ).hexdigest()


@dataclass(frozen=True)
class Refusal:
    """What the server answers instead of the request."""

    status: http.HTTPStatus
    body: bytes
    headers: tuple[tuple[str, str], ...] = ()


UNAUTHORIZED = Refusal(
    http.HTTPStatus.UNAUTHORIZED,
    b"this page needs its token: open the URL with ?token= that the operator node "
    b"or the demo printed when it started\n",
    (("WWW-Authenticate", 'Bearer realm="deepxpalm"'),),
)


@dataclass
class PageAuth:
    """The run's token and the names the page may be opened under; ``check`` each request."""

    token: str = field(default_factory=web_token.new_token)
    allowed_hosts: Iterable[str] = ()
    name: str = "page"
    _hosts: set[str] = field(default_factory=set, init=False)
    _any_address: bool = field(default=False, init=False)

    def __post_init__(self) -> None:
        web_token.check_token(self.token, f"{self.name} token")
        self.allowed_hosts = tuple(self.allowed_hosts)
        self._hosts = {_normal(h) for h in (*LOCAL_NAMES, *self.allowed_hosts)}

    def bind(self, host: str, port: int) -> None:
        """The server's address: its name joins the allowlist."""
        if host in WILDCARDS:
            self._any_address = True
        else:
            self._hosts.add(_normal(host))

    def check(self, target: str, headers: Mapping[str, str], websocket: bool) -> Refusal | None:
        """None when the request may be served (a WebSocket: opened, and then proven by its
        token or by the challenge, ``proven``); else what to answer."""
        host = headers.get("Host") or ""
        if not self.host_allowed(host):
            log.warning("%s: refused a request for host %r (not in the allowlist)", self.name, host)
            return Refusal(
                http.HTTPStatus.FORBIDDEN,
                f"host {host!r} is not one this page is served under: open it as "
                "127.0.0.1 or localhost, or add the name to dashboard.allowed_hosts\n".encode(),
            )
        origin = headers.get("Origin")
        if origin is not None and urlsplit(origin).netloc.lower() != host.lower():
            log.warning("%s: refused a request from origin %s", self.name, origin)
            return Refusal(http.HTTPStatus.FORBIDDEN, b"cross-origin\n")
        given = [t for t in (web_token.from_query(target), web_token.from_bearer(headers)) if t]
        if given:  # a token given must be the token, for a file too
            if all(web_token.matches(t, self.token) for t in given):
                return None
            log.info("%s: refused a wrong token (%s)", self.name, urlsplit(target).path)
            return UNAUTHORIZED
        if not websocket:
            return None  # the package's page files: nothing of the run, nothing to steer
        if CHALLENGE_PROTOCOL in offered_protocols(headers):
            return None  # the page: it proves the token on the socket, before anything else
        log.info("%s: refused a WebSocket without the token", self.name)
        return UNAUTHORIZED

    def proven(self, target: str, headers: Mapping[str, str]) -> bool:
        """Whether the request itself carries the token (a script); else the page's socket
        must answer the challenge."""
        given = (web_token.from_query(target), web_token.from_bearer(headers))
        return any(web_token.matches(t, self.token) for t in given)

    def answers(self, nonce: str, reply: object) -> bool:
        """Whether ``reply`` (the page's first message, parsed) proves the token for ``nonce``:
        ``{"type": "auth", "mac": challenge_mac(token, nonce)}``, or, from a page where the
        browser offers no HMAC (a plain-HTTP name that is not loopback), ``"token"``."""
        if not isinstance(reply, dict) or reply.get("type") != "auth":
            return False
        mac, token = reply.get("mac"), reply.get("token")
        if isinstance(mac, str):
            return web_token.matches(mac, challenge_mac(self.token, nonce))
        return isinstance(token, str) and web_token.matches(token, self.token)

    def host_allowed(self, host_header: str) -> bool:
        hostname = urlsplit(f"//{host_header}").hostname
        if not hostname:
            return False
        hostname = _normal(hostname)
        if hostname in self._hosts:
            return True
        if self._any_address:
            try:
                ipaddress.ip_address(hostname)
            except ValueError:
                return False
            return True
        return False


def offered_protocols(headers: Mapping[str, str]) -> list[str]:
    """The subprotocols a WebSocket request offers (``Sec-WebSocket-Protocol``)."""
    raw = headers.get("Sec-WebSocket-Protocol") or ""
    return [p.strip() for p in raw.split(",") if p.strip()]


def _normal(host: str) -> str:
    return host.strip().strip("[]").lower().rstrip(".")
