"""What must arrive arrives in a burst on a busy machine: commands and video signals.

Zenoh gives every express message a transmit batch of its own, and a message
under congestion control DROP waits 1 ms for a free batch before it is dropped,
reliable or not. With Zenoh's default of two batches a priority, bursts of
express messages (a viewer's offers, a jog beside a gripper command) lost some
whenever a busy machine kept a transmit thread off the cores for a millisecond.
The fabric's links give the kinds that must arrive Zenoh's largest queues
(``session.TX_QUEUE_BATCHES``).

A router and two clients, each with the transmit settings of the product's
links (``tx_section``), on a Unix socket (no port to choose); the product's
publisher and subscriber; two busy loops take the machine's cores while bursts
of commands and of video offers go through.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time

import pytest
import zenoh

from common.clocks.clock import now_ns
from common.fabric import keyexprs
from common.fabric.link import FabricPublisher, FabricSubscriber
from common.fabric.session import close_session, quiet_discovery, tx_section
from common.wire.messages import Command, Heartbeat, VideoSignal

#: alone: its busy loops take the cores the tests beside it would need
pytestmark = [pytest.mark.slow, pytest.mark.alone, pytest.mark.timeout(120)]

BURST = 8  # a viewer's offers at once, as the video privilege test sends them
ROUNDS = 30
SDP = "v=0\r\n" + "a=x-filler:" + "x" * 1200 + "\r\n"  # about an offer's size
ROBOT = b"cell1"


def _session(mode: str, path: str) -> object:
    side = "listen" if mode == "router" else "connect"
    config = {
        "mode": mode,
        side: {"endpoints": [f"unixsock-stream/{path}"]},
        "scouting": quiet_discovery(),
        "transport": {"link": {"tx": tx_section()}},
    }
    return zenoh.open(zenoh.Config.from_json5(json.dumps(config)))


def _message(kind: str, seq: int) -> Command | Heartbeat | VideoSignal:
    if kind == "command":
        return Command(seq=seq, t_send_ns=now_ns(), action="gripper_close", grip_level=5)
    if kind == "heartbeat":  # best-effort, but the robot's deadman and the lease count on it
        return Heartbeat(seq=seq, t_send_ns=now_ns(), node="operator", state="ok")
    return VideoSignal(seq=seq, t_send_ns=now_ns(), kind="offer", viewer=seq + 1, sdp=SDP)


@pytest.mark.parametrize("kind", ["command", "video", "heartbeat"])
def test_a_burst_of_what_must_arrive_arrives_beside_two_busy_loops(kind, tmp_path):
    path = str(tmp_path / "router.sock")
    router = _session("router", path)
    sender, receiver = _session("client", path), _session("client", path)
    key = keyexprs.operator_key(ROBOT, "ctl", kind)
    sub = FabricSubscriber(receiver, (key,), expect_name=ROBOT, latest_value=False)
    pub = FabricPublisher(sender, robot=ROBOT, operator="ctl")
    spin = "while True: pass"
    busy = [subprocess.Popen([sys.executable, "-c", spin]) for _ in range(2)]
    got: list[int] = []
    try:
        deadline = time.monotonic() + 10
        while not sub.drain():  # a first message through: the router knows the reader
            refused = sub.rejected
            assert time.monotonic() < deadline, f"nothing reached the subscriber: {refused}"
            pub.send(_message(kind, 0))
            time.sleep(0.05)
        time.sleep(0.2)
        sub.drain()  # the probes' stragglers
        seq = 0
        for _ in range(ROUNDS):
            for _ in range(BURST):
                seq += 1
                pub.send(_message(kind, seq))
            time.sleep(0.1)
        deadline = time.monotonic() + 10
        while len(got) < seq and time.monotonic() < deadline:
            sub.poll(0.1)
            got += [msg.seq for msg, _ in sub.drain()]
    finally:
        for p in busy:
            p.kill()
            p.wait()
        pub.close()
        sub.close()
        for s in (sender, receiver, router):
            close_session(s)
    lost = sorted(set(range(1, seq + 1)) - set(got))
    assert not lost, f"{len(lost)} of {seq} {kind} messages lost in bursts of {BURST}: {lost[:20]}"
