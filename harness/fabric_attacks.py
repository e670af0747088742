"""Attacks on the fabric from one member's key, each in a process of its own.

An attacker is another machine: its flood must cost the fleet what it costs
through the router, not the interpreter lock or the Zenoh runtime of the
process that watches the robots. ``Attacker`` runs one of ``ATTACKS`` in a
child process (spawned: a fresh interpreter and Zenoh runtime) with the
member's certificate, says when its session is open, and hands back what
it heard when told to end.
"""

from __future__ import annotations

import multiprocessing
import os
import time
from collections.abc import Callable
from multiprocessing.synchronize import Event
from typing import Any

from common.clocks.clock import now_ns
from common.fabric import keyexprs
from common.fabric.session import FabricConfig, cert_files, client_config, open_session
from common.wire.codec import MAX_MESSAGE_BYTES, encode
from common.wire.messages import Command, Heartbeat

ROBOTS = ("cell1", "cell2")


def open_member_session(router_endpoint: str, cert_dir: str, member: str) -> Any:
    """A Zenoh client session to the router with ``member``'s certificate."""
    fabric = FabricConfig(router_endpoint=router_endpoint, retry_ms=50.0)
    files = cert_files(cert_dir, member, "test")
    return open_session(client_config(fabric, files, "test"), f"attacker as {member}")


def forge_another_robot(session: Any, done: Event) -> list[str]:
    """A robot key (cell1's) puts cell2's stream and STOPs to cell2 as its controller."""
    forged = encode(Heartbeat(seq=1, t_send_ns=now_ns(), node="robot", state="ok"), b"cell2")
    while not done.is_set():
        for kind in ("stimulus", "heartbeat", "video"):
            session.put(keyexprs.robot_key("cell2", kind), forged)
        session.put(keyexprs.operator_key("cell2", "c", keyexprs.STOP), forged)
        time.sleep(0.001)
    return []


def read_with_wildcards(session: Any, done: Event) -> list[str]:
    """An observer subscribes to everything it can name; the keys it heard."""
    heard: list[str] = []
    subs = [
        session.declare_subscriber(k, lambda s: heard.append(str(s.key_expr)))
        for k in ("dxp/**", "dxp/*/op/**", "dxp/cell2/op/c/stop", "**")
    ]
    done.wait()
    for sub in subs:
        sub.undeclare()
    return heard


#: the junk flood's puts a second: a hundred times what the router's gates pass an operator's
#: stop and heartbeat keys, and what a remote attacker's uplink carries of small messages. Unpaced
#: it took a whole core of the two the test's deployments share (the router among them), which a
#: remote attacker cannot: that measured the test machine, not the router's isolation
FLOOD_PUTS_PER_S = 10_000


def flood_junk(session: Any, done: Event) -> list[str]:
    """An observer puts junk, oversized payloads and a replayed STOP, ``FLOOD_PUTS_PER_S``."""
    big = b"\x00" * (MAX_MESSAGE_BYTES + 1)
    stop = encode(Command(seq=1, t_send_ns=now_ns(), action="arm_stop", session=1), b"cell2")
    n = 0
    round_s = len(ROBOTS) * 5 / FLOOD_PUTS_PER_S  # five puts per robot a round
    next_t = time.monotonic()
    while not done.is_set():
        next_t += round_s
        if (ahead := next_t - time.monotonic()) > 0:
            time.sleep(ahead)
        for robot in ROBOTS:
            for kind in (keyexprs.STOP, "heartbeat", "command", "video"):
                key = keyexprs.operator_key(robot, "mallory", kind)
                session.put(key, big if n % 50 == 0 else b"junk" + n.to_bytes(4, "big"))
            session.put(keyexprs.operator_key(robot, "mallory", keyexprs.STOP), stop)
        n += 1
    return []


def churn_connections(session: Any, done: Event, reopen: Callable[[], Any]) -> list[str]:
    """Sessions opened and closed, each declaring 200 subscribers the ACL does not filter."""
    session.close()
    while not done.is_set():
        s = reopen()
        for i in range(200):
            s.declare_subscriber(f"dxp/cell{i}/stimulus", lambda _s: None)
        s.close()
    return []


ATTACKS: dict[str, Callable[..., list[str]]] = {
    "forge_another_robot": forge_another_robot,
    "read_with_wildcards": read_with_wildcards,
    "flood_junk": flood_junk,
    "churn_connections": churn_connections,
}


#: the attacker's niceness: it stands for another machine, whose CPU is not ours to give. At
#: the tests' own priority its flood took a core of the deployments it attacks on a 2-core
#: machine, which a remote attacker cannot; what it costs the router is what is measured.
ATTACKER_NICE = 19


def _run(
    name: str, router_endpoint: str, cert_dir: str, member: str, opened: Event, done: Event, out
) -> None:
    os.nice(ATTACKER_NICE - os.nice(0))

    def reopen() -> Any:
        return open_member_session(router_endpoint, cert_dir, member)

    session = reopen()
    opened.set()
    attack = ATTACKS[name]
    extra = (reopen,) if name == "churn_connections" else ()
    try:
        out.send(("heard", attack(session, done, *extra)))
    except Exception as e:  # the parent reports it as the test's failure
        out.send(("error", f"{type(e).__name__}: {e}"))
    if name != "churn_connections":
        session.close()


class Attacker:
    """One attack in a spawned process; ``start`` returns once its session is open."""

    def __init__(self, name: str, router_endpoint: str, cert_dir: str, member: str) -> None:
        if name not in ATTACKS:
            raise ValueError(f"no attack {name!r}: one of {', '.join(ATTACKS)}")
        ctx = multiprocessing.get_context("spawn")
        self._opened = ctx.Event()
        self._done = ctx.Event()
        self._recv, send = ctx.Pipe(duplex=False)
        self._proc = ctx.Process(
            target=_run,
            args=(name, router_endpoint, str(cert_dir), member, self._opened, self._done, send),
            daemon=True,
            name=f"attack-{name}",
        )

    def start(self, timeout_s: float = 60.0) -> Attacker:
        self._proc.start()
        if not self._opened.wait(timeout_s):
            self._proc.kill()
            raise RuntimeError("the attacker's session never opened")
        return self

    def end(self, timeout_s: float = 15.0) -> list[str]:
        """Tell the attack to end; the keys it heard (attacks that read)."""
        self._done.set()
        if not self._recv.poll(timeout_s):
            self._proc.kill()
            raise RuntimeError("the attacker did not end when told")
        what, value = self._recv.recv()
        self._proc.join(timeout_s)
        if what == "error":
            raise RuntimeError(f"the attack failed: {value}")
        return value
