"""Where the video's media sockets listen: only the configured interfaces, and no mDNS.

aiortc gathers a host candidate on every address of every interface (aioice's
``get_host_addresses``; loopback excluded), so while a viewer watches, its
UDP sockets listen on every network the robot PC is on. Neither aiortc
1.16 nor aioice 0.13 has a setting for that (``RTCConfiguration`` has only
the ICE servers and the transport policy; aioice's ``use_ipv4``/``use_ipv6``
are not even passed through), so ``restrict`` wraps that one function: on
the video server's loop (a context variable, set there) it returns the
configured addresses instead; everywhere else it is aioice's own.

A browser names its host candidates by mDNS (``<uuid>.local``); resolving
one makes aioice open a listener on 0.0.0.0:5353. The video server drops
such candidates from the offer instead: the browser's connectivity checks
still reach our candidates, and ICE learns the browser's address from them
(a peer-reflexive candidate, RFC 8445 section 7.3.1.3).
"""

from __future__ import annotations

import contextvars
import ipaddress
import logging
import re
from collections.abc import Iterable

from common.errors import ConfigError

log = logging.getLogger(__name__)

_allowed: contextvars.ContextVar[tuple[str, ...] | None] = contextvars.ContextVar(
    "video_media_addresses", default=None
)
_MDNS_CANDIDATE = re.compile(r"^a=candidate:\S+ \d+ \S+ \d+ [A-Za-z0-9-]+\.local \d+ .*$")


def addresses(interfaces: Iterable[str]) -> tuple[str, ...]:
    """The addresses of ``interfaces`` (names like ``eth0``, or addresses of this machine)."""
    import ifaddr  # aioice's own dependency

    adapters = {a.name: a for a in ifaddr.get_adapters()}
    local = {_address(ip) for a in adapters.values() for ip in a.ips if _usable(ip)}
    out: list[str] = []
    for entry in interfaces:
        if _is_address(entry):
            ip = str(ipaddress.ip_address(entry))
            if ip not in local:
                raise ConfigError(
                    f"video media_interfaces: {ip} is not an address of this machine "
                    f"(it has {', '.join(sorted(local))})"
                )
            found = [ip]
        else:
            adapter = adapters.get(entry)
            if adapter is None:
                raise ConfigError(
                    f"video media_interfaces: no interface {entry!r} on this machine "
                    f"(there are {', '.join(sorted(adapters))})"
                )
            found = [_address(ip) for ip in adapter.ips if _usable(ip)]
            if not found:
                raise ConfigError(f"video media_interfaces: interface {entry!r} has no address")
        out += [a for a in found if a not in out]
    return tuple(out)


def restrict(allowed: tuple[str, ...]) -> None:
    """From now on, peer connections created in this context gather only ``allowed``."""
    _install()
    _allowed.set(allowed)


def without_mdns_candidates(sdp: str) -> str:
    """``sdp`` without the ``a=candidate`` lines that name a host by mDNS."""
    lines = sdp.split("\r\n")
    kept = [line for line in lines if not _MDNS_CANDIDATE.match(line)]
    if len(kept) != len(lines):
        log.debug("video: dropped %d mDNS candidate(s) of a viewer", len(lines) - len(kept))
    return "\r\n".join(kept)


def _install() -> None:
    import aioice.ice

    original = aioice.ice.get_host_addresses
    if getattr(original, "deepxpalm_restricted", False):
        return

    def host_addresses(use_ipv4: bool, use_ipv6: bool) -> list[str]:
        allowed = _allowed.get()
        if allowed is None:
            return original(use_ipv4=use_ipv4, use_ipv6=use_ipv6)
        return [a for a in allowed if (use_ipv6 if ":" in a else use_ipv4)]

    host_addresses.deepxpalm_restricted = True  # type: ignore[attr-defined]
    aioice.ice.get_host_addresses = host_addresses


def _is_address(entry: str) -> bool:
    try:
        ipaddress.ip_address(entry)
    except ValueError:
        return False
    return True


def _usable(ip: object) -> bool:
    """IPv4, or IPv6 without a scope (a link-local address needs one; aioice skips them too)."""
    return isinstance(ip.ip, str) or ip.ip[2] == 0  # type: ignore[attr-defined]


def _address(ip: object) -> str:
    value = ip.ip  # type: ignore[attr-defined]
    return value if isinstance(value, str) else value[0]
