"""Who may open a page: the run's token, and only under a name this machine answers to.

Every request (the page, its scripts, its WebSocket) must carry the token:
``?token=`` in the URL printed at start (then a cookie, so a reload and a
second tab need nothing more), an ``Authorization: Bearer`` header, or that
cookie. Without it: 401, nothing served, no socket.

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

import http
import ipaddress
import logging
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from http.cookies import CookieError, SimpleCookie
from urllib.parse import urlsplit

from common import web_token

log = logging.getLogger(__name__)

LOCAL_NAMES = ("127.0.0.1", "localhost", "::1")
WILDCARDS = ("", "0.0.0.0", "::")


@dataclass(frozen=True)
class Refusal:
    """What the server answers instead of the request (a refusal or the cookie's redirect)."""

    status: http.HTTPStatus
    body: bytes
    headers: tuple[tuple[str, str], ...] = ()


@dataclass
class PageAuth:
    """The run's token and the names the page may be opened under; ``check`` each request."""

    token: str = field(default_factory=web_token.new_token)
    allowed_hosts: Iterable[str] = ()
    name: str = "page"
    cookie: str = "dxp-page"
    _hosts: set[str] = field(default_factory=set, init=False)
    _any_address: bool = field(default=False, init=False)

    def __post_init__(self) -> None:
        web_token.check_token(self.token, f"{self.name} token")
        self.allowed_hosts = tuple(self.allowed_hosts)
        self._hosts = {_normal(h) for h in (*LOCAL_NAMES, *self.allowed_hosts)}

    def bind(self, host: str, port: int) -> None:
        """The server's address: its name joins the allowlist, its port names the cookie.

        The cookie's name carries the port because browsers share cookies
        between the ports of a host (the dashboard and the study page).
        """
        if host in WILDCARDS:
            self._any_address = True
        else:
            self._hosts.add(_normal(host))
        self.cookie = f"dxp-page-{port}"

    def check(self, target: str, headers: Mapping[str, str], websocket: bool) -> Refusal | None:
        """None when the request may be served; else what to answer."""
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
        in_query = web_token.from_query(target)
        if web_token.matches(in_query, self.token) and not websocket:
            # the token leaves the address bar (and the history); the cookie keeps it
            return Refusal(
                http.HTTPStatus.SEE_OTHER,
                b"",
                (
                    ("Location", web_token.without_token(target)),
                    (
                        "Set-Cookie",
                        f"{self.cookie}={self.token}; Path=/; HttpOnly; SameSite=Strict",
                    ),
                ),
            )
        given = [in_query, web_token.from_bearer(headers), self._from_cookie(headers)]
        if any(web_token.matches(t, self.token) for t in given):
            return None
        log.info("%s: refused a request without the token (%s)", self.name, urlsplit(target).path)
        return Refusal(
            http.HTTPStatus.UNAUTHORIZED,
            b"this page needs its token: open the URL with ?token= that the operator node "
            b"or the demo printed when it started\n",
            (("WWW-Authenticate", 'Bearer realm="deepxpalm"'),),
        )

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

    def _from_cookie(self, headers: Mapping[str, str]) -> str | None:
        raw = headers.get("Cookie")
        if not raw:
            return None
        jar: SimpleCookie = SimpleCookie()
        try:
            jar.load(raw)
        except CookieError:
            return None
        morsel = jar.get(self.cookie)
        return None if morsel is None else morsel.value


def _normal(host: str) -> str:
    return host.strip().strip("[]").lower().rstrip(".")
