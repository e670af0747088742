"""One robot's key cannot pose as another robot through the relay (names bound to keys).

A real relay process (CURVE, the roster) and raw clients holding the
fleet's own keys: what the attacker's key sends and what it reads is judged
at the other clients, outside the relay. Each test has its control: the
same flow from the right key goes through in the same run.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
import zmq

from common.codec import decode_named, encode, name_prefix
from common.messages import Command, Heartbeat, Stimulus
from common.security import SecurityConfig, client_options
from common.transport import Publisher
from harness.fleet import Fleet

pytestmark = [pytest.mark.slow, pytest.mark.timeout(60), pytest.mark.parallel]

#: a posing message's seq: whatever reaches a subscriber with one came from the attacker
POSING = 10**6


def _stimulus(seq: int) -> Stimulus:
    t = time.monotonic_ns()
    return Stimulus(
        seq=seq,
        t_send_ns=t,
        t_capture_ns=t,
        frame_seq=seq,
        mode="mask",
        contact=True,
        stimulus=np.eye(3, dtype=np.float32),
        pattern=3,
    )


def _socket(ctx: zmq.Context, fleet: Fleet, kind: int, member: str, endpoint: str) -> zmq.Socket:
    sock = ctx.socket(kind)
    sock.setsockopt(zmq.LINGER, 0)
    for opt, value in client_options(SecurityConfig(**fleet.client_security(member))).items():
        sock.setsockopt(opt, value)
    sock.connect(endpoint)
    return sock


def _received(sock: zmq.Socket) -> list[tuple[bytes, object]]:
    out = []
    while sock.poll(0):
        out.append(decode_named(sock.recv()))
    return out


def _pump_until(cond, send, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        send()
        time.sleep(0.01)


@pytest.fixture
def fleet(tmp_path):
    fleet = Fleet(
        robots=["cell1", "cell2"],
        operators={"alice": "controller", "obs": "observer"},
        workdir=tmp_path,
    )
    with fleet:
        relay = fleet.start_relay()
        fleet.wait_for(lambda: "relay up" in relay.log_text(), 30, "the relay")
        yield fleet


def test_cell2s_key_publishing_as_cell1_reaches_none_of_cell1s_subscribers(fleet):
    ctx = zmq.Context()
    watcher = _socket(ctx, fleet, zmq.SUB, "obs", fleet.ops_telemetry)
    for name in (b"cell1", b"cell2"):
        for topic in (Stimulus.TOPIC, Heartbeat.TOPIC):
            watcher.setsockopt(zmq.SUBSCRIBE, name_prefix(topic, name))
    cell1 = _socket(ctx, fleet, zmq.PUB, "cell1", fleet.robots_telemetry)
    cell2 = _socket(ctx, fleet, zmq.PUB, "cell2", fleet.robots_telemetry)
    got: list[tuple[bytes, object]] = []
    seq = 0

    def send_all() -> None:
        nonlocal seq
        seq += 1
        cell1.send(encode(_stimulus(seq), b"cell1"))
        cell2.send(encode(_stimulus(seq), b"cell2"))  # its own name: the control
        cell2.send(encode(_stimulus(POSING + seq), b"cell1"))  # posing as cell1
        hb = Heartbeat(POSING + seq, time.monotonic_ns(), "robot", "ok", lease_holder=bytes(32))
        cell2.send(encode(hb, b"cell1"))  # a forged lease holder for cell1's dashboards
        got.extend(_received(watcher))

    try:
        own = lambda name: [m for n, m in got if n == name and m.seq < POSING]  # noqa: E731
        _pump_until(lambda: own(b"cell1") and own(b"cell2"), send_all, 20, "both robots' flow")
        posed_from = seq
        for _ in range(150):  # 1.5 s at 100 Hz
            send_all()
            time.sleep(0.01)
        time.sleep(0.2)
        got.extend(_received(watcher))
    finally:
        for sock in (watcher, cell1, cell2):
            sock.close(0)
        ctx.term()
    posing = [m for n, m in got if m.seq >= POSING]
    assert posing == [], f"{len(posing)} posing messages reached cell1's subscriber"
    after = lambda name: [m for m in own(name) if m.seq > posed_from]  # noqa: E731
    assert len(after(b"cell1")) > 100 and len(after(b"cell2")) > 100, "the control flows"
    relay = fleet.procs["relay"]
    fleet.stop("relay")
    stats = relay.stats()
    assert stats["telemetry_dropped_name"] >= 2 * 150, stats
    assert "a robot key posing" in relay.log_text()
    assert "as robot cell1; it may use cell2" in relay.log_text()


def test_cell2s_key_reads_none_of_cell1s_commands(fleet):
    ctx = zmq.Context()
    alice = Publisher(
        ctx,
        fleet.ops_command,
        bind=False,
        sock_opts=client_options(SecurityConfig(**fleet.client_security("alice"))),
    )
    cell1 = _socket(ctx, fleet, zmq.SUB, "cell1", fleet.robots_command)
    cell1.setsockopt(zmq.SUBSCRIBE, name_prefix(Command.TOPIC, b"cell1"))
    cell2 = _socket(ctx, fleet, zmq.SUB, "cell2", fleet.robots_command)
    # every way to ask for cell1's commands, and its own: only the last is granted
    for prefix in (
        name_prefix(Command.TOPIC, b"cell1"),
        name_prefix(Heartbeat.TOPIC, b"cell1"),
        name_prefix(Command.TOPIC, b"cell1")[:-1],  # "cell" is a prefix of "cell1"
        Command.TOPIC,
        b"",
        name_prefix(Command.TOPIC, b"cell2"),
    ):
        cell2.setsockopt(zmq.SUBSCRIBE, prefix)
    at1: list[tuple[bytes, object]] = []
    at2: list[tuple[bytes, object]] = []
    seq = 0

    def send_all() -> None:
        nonlocal seq
        seq += 1
        for name in (b"cell1", b"cell2"):
            cmd = Command(seq=seq, t_send_ns=time.monotonic_ns(), action="gripper_open")
            alice.send_raw(encode(cmd, name))
            hb = Heartbeat(seq, time.monotonic_ns(), "operator", "ok")
            alice.send_raw(encode(hb, name))
        at1.extend(_received(cell1))
        at2.extend(_received(cell2))

    try:
        _pump_until(lambda: at1 and at2, send_all, 20, "both robots' commands")
        for _ in range(150):
            send_all()
            time.sleep(0.01)
        time.sleep(0.2)
        at1.extend(_received(cell1))
        at2.extend(_received(cell2))
    finally:
        for sock in (cell1, cell2):
            sock.close(0)
        alice.close()
        ctx.term()
    stolen = [m for n, m in at2 if n != b"cell2"]
    assert stolen == [], f"cell2's key read {len(stolen)} of cell1's commands"
    assert len([m for n, m in at2 if isinstance(m, Command)]) > 100, "cell2's own arrive"
    assert len([m for n, m in at1 if n == b"cell1"]) > 100, "cell1 gets its commands"
    relay = fleet.procs["relay"]
    fleet.stop("relay")
    assert relay.stats()["commands_subscriptions_refused_name"] >= 5, relay.stats()
    assert "asked for b'CMND' of robot cell1; it may use cell2" in relay.log_text()
