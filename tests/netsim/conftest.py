"""A fake robot and operator on loopback around a ``LinkSimulator``."""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass

import pytest
import zmq

from common.netsim.impairments import Scenario
from common.netsim.proxy import Endpoints, LinkSimulator

RECV_TIMEOUT_MS = 2000


def _sock(ctx: zmq.Context, kind: int) -> zmq.Socket:
    s = ctx.socket(kind)
    s.setsockopt(zmq.LINGER, 0)
    s.setsockopt(zmq.RCVTIMEO, RECV_TIMEOUT_MS)
    if kind == zmq.SUB:
        s.setsockopt(zmq.SUBSCRIBE, b"")
    return s


@dataclass
class Link:
    """The four node-side sockets, already connected through the simulator."""

    sim: LinkSimulator
    robot_pub: zmq.Socket
    robot_sub: zmq.Socket
    operator_sub: zmq.Socket
    operator_pub: zmq.Socket

    def recv(self, sock: zmq.Socket, timeout_s: float = 2.0) -> bytes | None:
        if sock.poll(int(timeout_s * 1000)):
            return sock.recv(zmq.NOBLOCK)
        return None


def _wait_joined(pub: zmq.Socket, sub: zmq.Socket, deadline_s: float = 5.0) -> None:
    """Defeat the slow joiner: publish probes until one arrives, then drain."""
    t_end = time.monotonic() + deadline_s
    while time.monotonic() < t_end:
        pub.send(b"PRBE")
        if sub.poll(20):
            break
    else:
        raise TimeoutError("subscription through the simulator never completed")
    while sub.poll(50):  # the probes still in flight (a test that reads content skips later ones)
        sub.recv()


@pytest.fixture
def make_link() -> Iterator:
    """``make_link(scenario, seed)`` -> a connected ``Link``; everything closed after."""
    ctx = zmq.Context()
    sims: list[LinkSimulator] = []

    def _make(scenario: Scenario | None = None, seed: int = 0) -> Link:
        robot_pub = _sock(ctx, zmq.PUB)
        robot_pub.bind("tcp://127.0.0.1:*")
        robot_sub = _sock(ctx, zmq.SUB)
        robot_sub.bind("tcp://127.0.0.1:*")
        ep = Endpoints(
            robot_telemetry=robot_pub.getsockopt(zmq.LAST_ENDPOINT).decode(),
            robot_commands=robot_sub.getsockopt(zmq.LAST_ENDPOINT).decode(),
            operator_telemetry="tcp://127.0.0.1:*",
            operator_commands="tcp://127.0.0.1:*",
        )
        sim = LinkSimulator(scenario, endpoints=ep, seed=seed)
        sims.append(sim)
        sim.start()
        operator_sub = _sock(ctx, zmq.SUB)
        operator_sub.connect(sim.operator_telemetry_endpoint)
        operator_pub = _sock(ctx, zmq.PUB)
        operator_pub.connect(sim.operator_commands_endpoint)
        _wait_joined(robot_pub, operator_sub)
        _wait_joined(operator_pub, robot_sub)
        return Link(sim, robot_pub, robot_sub, operator_sub, operator_pub)

    try:
        yield _make
    finally:
        for sim in sims:
            sim.stop()
        ctx.destroy(linger=0)
