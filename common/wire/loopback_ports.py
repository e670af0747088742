"""Loopback ports known in advance, for the endpoints that must be named before a bind."""

from __future__ import annotations

#: Where ports known in advance are drawn: from here up to the kernel's ephemeral range.
KNOWN_PORTS_FROM = 10000


def _ephemeral_low(path: str = "/proc/sys/net/ipv4/ip_local_port_range") -> int | None:
    """The lowest port the kernel hands out on its own (a bind to port 0, a connect)."""
    try:
        with open(path) as f:
            return int(f.read().split()[0])
    except (OSError, ValueError, IndexError):
        return None


def free_loopback_ports(n: int, host: str = "127.0.0.1", *, udp: bool = False) -> list[int]:
    """``n`` TCP ports free on ``host`` right now (for endpoints that must be known in advance).

    Drawn at random below the kernel's ephemeral range: a port there can only be taken by a
    process that names it. A port the kernel picked itself (a bind to port 0) was free only
    until the probe closed it: any process's next bind to port 0, or an outgoing
    connection's source port, could take it before the caller bound it (a robot node's
    bind failed that way beside two other deployments). Each port is bound once here to
    check that nothing listens on it. Where the range leaves no room below it, the kernel
    picks. ``udp``: UDP ports (a QUIC listener's), checked by a UDP bind.
    """
    import random
    import socket

    low = _ephemeral_low()
    room = low is not None and low - KNOWN_PORTS_FROM >= 1000
    draws = random.SystemRandom()
    socks: list[socket.socket] = []
    try:
        for _ in range(100 * n):
            if len(socks) == n:
                break
            s = socket.socket(type=socket.SOCK_DGRAM if udp else socket.SOCK_STREAM)
            try:
                s.bind((host, draws.randrange(KNOWN_PORTS_FROM, low) if room else 0))
            except OSError:  # in use (or in TIME_WAIT): draw again
                s.close()
                if not room:
                    raise
                continue
            socks.append(s)
        if len(socks) < n:
            raise OSError(f"no {n} free ports on {host} in {KNOWN_PORTS_FROM}..{low - 1}")
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()
