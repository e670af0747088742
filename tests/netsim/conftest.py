"""A fake robot and operator on loopback around a ``LinkSimulator``."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import pytest
import zmq

from common.netsim.fidelity import FidelityRun
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
    time.sleep(0.05)
    while sub.poll(0):
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


#: Percentiles that one stalled process on a loaded 2-core machine can move by milliseconds.
TAIL_VERDICTS = ("p95", "p99")


def on_this_machine(run: FidelityRun) -> dict[str, bool]:
    """The run's verdicts scaled to what one hop costs here (``FidelityRun.scaled_verdicts``)."""
    return run.scaled_verdicts()


#: Measurements a fidelity test takes at most: another job on the machine can stall one.
ATTEMPTS = 3


def _figures(run: FidelityRun) -> str:
    """The run in one line, every figure kept (pytest cuts a long dict's repr)."""
    d = run.as_dict()
    parts = []
    for key in ("direct_ms", "configured_ms", "via_ms"):
        parts.append(f"{key} " + " / ".join(f"{k} {v:.3f}" for k, v in d[key].items()))
    parts.append(f"verdicts {on_this_machine(run)}")
    return "; ".join(parts)


@pytest.fixture
def assert_faithful():
    """Check a ``FidelityRun``: its median unless the machine is saturated, its tails unless
    it is overloaded.

    A short stall of one process by another job (a CI runner may share the
    machine) moves a 6 s measurement's median without moving the load
    average, so a run that fails is measured again, up to ``ATTEMPTS`` in
    all, and the first that meets every criterion passes; if none does, the
    last one is judged. With more runnable processes than cores (load
    average above the core count), any process, the direct path's included,
    waits milliseconds for a core now and then; the tails then measure the
    machine, not the simulator, and the test skips their check saying so.
    Above 1.5 runnable processes a core (two busy loops beside it on two
    cores) the median waits too, and the test skips whatever failed, saying
    so. The bench table is the record.
    """
    import os

    def check(run: FidelityRun, remeasure: Callable[[], FidelityRun]) -> None:
        tried = [run]
        while not all(on_this_machine(run).values()) and len(tried) < ATTEMPTS:
            run = remeasure()
            tried.append(run)
        summary = f"{len(tried)} measurement(s), the last: {_figures(run)}"
        if len(tried) > 1:
            summary += "; before it: " + " | ".join(_figures(r) for r in tried[:-1])
        assert len(run.via_ms) >= 0.99 * run.seconds * run.rate_hz, summary
        verdicts = on_this_machine(run)
        load, cores = os.getloadavg()[0], os.cpu_count() or 1
        if not all(verdicts.values()) and load > 1.5 * cores:
            # two busy loops on two cores: the relay process gets two thirds of a core and
            # even its median waits for one; measured again, this is the machine
            pytest.skip(f"not checkable at load average {load:.1f} on {cores} cores: {summary}")
        medians_ok = all(ok for k, ok in verdicts.items() if k not in TAIL_VERDICTS)
        assert medians_ok, f"at load average {load:.1f} on {cores} cores: {summary}"
        tails_ok = all(ok for k, ok in verdicts.items() if k in TAIL_VERDICTS)
        if not tails_ok and load > cores:
            pytest.skip(
                f"tails not checkable at load average {load:.1f} on {cores} cores: {summary}"
            )
        assert tails_ok, f"at load average {load:.1f} on {cores} cores: {summary}"

    return check
