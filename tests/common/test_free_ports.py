"""Ports known in advance: drawn where only a process that names them can take them."""

from __future__ import annotations

import socket

from common.wire import loopback_ports
from common.wire.loopback_ports import KNOWN_PORTS_FROM, free_loopback_ports


def test_ports_come_from_below_the_kernels_own_range_distinct_and_free():
    low = loopback_ports._ephemeral_low()
    assert low is not None and low - KNOWN_PORTS_FROM >= 1000, "a Linux range, as in CI"
    ports = free_loopback_ports(8)
    assert len(set(ports)) == 8
    assert all(KNOWN_PORTS_FROM <= p < low for p in ports), ports
    for p in ports:  # each one binds, as the node that was given it will
        with socket.socket() as s:
            s.bind(("127.0.0.1", p))


def _a_free_port(start: int) -> int:
    for port in range(start, start + 1000):
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    raise AssertionError(f"no free port in {start}..{start + 999}")


def test_a_port_someone_listens_on_is_never_handed_out(monkeypatch):
    """The draw meets a listening port first, and draws again."""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", _a_free_port(KNOWN_PORTS_FROM)))
        taken.listen()
        busy = taken.getsockname()[1]
        free = _a_free_port(busy + 1)
        draws = iter([busy, free])

        class Scripted:
            def randrange(self, _lo, _hi):
                return next(draws)

        monkeypatch.setattr("random.SystemRandom", Scripted)
        assert free_loopback_ports(1) == [free]


def test_without_room_below_the_range_the_kernel_picks(monkeypatch):
    monkeypatch.setattr(loopback_ports, "_ephemeral_low", lambda: KNOWN_PORTS_FROM + 10)
    (port,) = free_loopback_ports(1)
    assert port > 0
    with socket.socket() as s:
        s.bind(("127.0.0.1", port))
