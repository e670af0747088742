"""A command flood from a client written from docs/protocol.md alone (raw pyzmq and msgpack).

Runs in its own process (``run`` is the process target): it syncs clocks with
the robot by echoing heartbeats, jogs the arm for a moment as an operator
would, then sends ``n`` valid ``arm_jog`` commands as fast as it can, keeping
its heartbeats going, and reports when its first and last flood messages left.
"""

from __future__ import annotations

import time

import msgpack
import zmq

SESSION = 31337


def _heartbeat(seq: int, echo: tuple[int, int] | None) -> bytes:
    body = {"v": 1, "type": "heartbeat", "seq": seq, "t_send_ns": time.monotonic_ns()}
    body.update(node="operator", state="ok")
    if echo is not None:
        body.update(echo_t_send_ns=echo[0], echo_t_recv_ns=echo[1])
    return b"HBRT" + msgpack.packb(body)


def _jog(seq: int, velocity: list[float]) -> bytes:
    body = {"v": 1, "type": "command", "seq": seq, "t_send_ns": time.monotonic_ns()}
    body.update(action="arm_jog", velocity=velocity, session=SESSION)
    return b"CMND" + msgpack.packb(body)


def run(telemetry: str, commands: str, n: int, velocity: list[float], conn) -> None:
    ctx = zmq.Context()
    sub = ctx.socket(zmq.SUB)
    sub.setsockopt(zmq.LINGER, 0)
    sub.setsockopt(zmq.SUBSCRIBE, b"HBRT")
    sub.connect(telemetry)
    pub = ctx.socket(zmq.PUB)
    pub.setsockopt(zmq.LINGER, 0)
    pub.connect(commands)
    state = {"echo": None, "hb": 0, "next_hb": 0, "first_echoing": None, "synced": False}

    def tend() -> None:
        """Read the robot's heartbeats (non-blocking) and send ours every 50 ms."""
        while sub.poll(0):
            data = sub.recv()
            body = msgpack.unpackb(data[4:])
            state["echo"] = (body["t_send_ns"], time.monotonic_ns())
            first, echoed = state["first_echoing"], body.get("echo_t_send_ns")
            if first is not None and echoed is not None and echoed >= first:
                state["synced"] = True  # it read a heartbeat of ours that echoed one of its own
        now = time.monotonic_ns()
        if now >= state["next_hb"]:
            state["hb"] += 1
            if state["echo"] is not None and state["first_echoing"] is None:
                state["first_echoing"] = now
            pub.send(_heartbeat(state["hb"], state["echo"]))
            state["next_hb"] = now + 50_000_000

    seq = 0
    # heartbeats until the robot knows our clock: a round trip it has answered, however
    # long a loaded machine takes, and never less than 0.8 s
    start = time.monotonic()
    while time.monotonic() < start + 0.8 or (not state["synced"] and time.monotonic() < start + 15):
        tend()
        time.sleep(0.005)
    end = time.monotonic() + 0.6  # an operator jogging, renewed every 50 ms
    while time.monotonic() < end:
        seq += 1
        pub.send(_jog(seq, velocity))
        tend()
        time.sleep(0.05)
    t_first = time.monotonic_ns()
    for i in range(n):
        seq += 1
        pub.send(_jog(seq, velocity))
        if i % 256 == 0:
            tend()
    t_last = time.monotonic_ns()
    conn.send({"t_first_ns": t_first, "t_last_ns": t_last, "sent": n})
    sub.close(0)
    pub.close(0)
    ctx.term()
