"""One key, one voice: what one robot or observer key sends through the relay disturbs nobody else.

A real relay process (CURVE, the roster) and two real robot nodes; the
attacker is the test itself holding one legitimate key (cell1's robot key, an
observer's key). What the other peers get is judged outside the relay: cell2's
own count of the controller's commands (in its heartbeats, read through the
relay as any operator reads them), and the robots' raw frames arriving on the
observers' own connections. One fleet for the module; the last test restarts
its relay.

``DEEPXPALM_VOICE_AFTER_S`` sets how long the flows are measured after each
attack (default 3 s; the issue's figure is 30 s).
"""

from __future__ import annotations

import contextlib
import os
import socket
import threading
import time
from pathlib import Path

import pytest
import zmq

from common.clock import now_ns
from common.codec import decode_named, name_prefix
from common.messages import Command, Heartbeat, TactileFrame, VideoSignal
from common.security import SecurityConfig, client_options
from harness.fleet import Fleet

pytestmark = [pytest.mark.slow, pytest.mark.timeout(180)]

AFTER_S = float(os.environ.get("DEEPXPALM_VOICE_AFTER_S", "3"))
#: the controller's commands a second in the test (the issue's controller sent 20)
COMMAND_HZ = 20.0
#: the fleet's robots send raw frames on this grid while someone wants them (harness/fleet.py)
FRAME_HZ = 15.0
ROBOTS = ("cell1", "cell2")
#: how long the relay may take to log a connection it ended (its log summarises bursts once
#: a second; a loaded machine has taken over one)
LOG_WITHIN_S = 10.0


def _socket(ctx: zmq.Context, fleet: Fleet, kind: int, member: str, endpoint: str) -> zmq.Socket:
    sock = ctx.socket(kind)
    sock.setsockopt(zmq.LINGER, 0)
    for opt, value in client_options(SecurityConfig(**fleet.client_security(member))).items():
        sock.setsockopt(opt, value)
    sock.connect(endpoint)
    return sock


def _rss_kb(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise AssertionError(f"no VmRSS for pid {pid}")


class Wire:
    """A member's own connection to the operators' side of the relay: (robot, message, arrival)."""

    def __init__(self, fleet: Fleet, key: str, topics: tuple[bytes, ...]) -> None:
        self.ctx = zmq.Context()
        self.sock = _socket(self.ctx, fleet, zmq.SUB, key, fleet.ops_telemetry)
        for robot in ROBOTS:
            for topic in topics:
                self.sock.setsockopt(zmq.SUBSCRIBE, name_prefix(topic, robot.encode()))
        self.got: list[tuple[str, object, int]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            if self.sock.poll(50):
                while self.sock.poll(0):
                    name, msg = decode_named(self.sock.recv())
                    self.got.append((name.decode(), msg, now_ns()))

    def count(self, robot: str, kind: type, t0: int, t1: int) -> int:
        return sum(
            1 for r, m, t in list(self.got) if r == robot and isinstance(m, kind) and t0 <= t < t1
        )

    def robot_stats(self, robot: str, after_ns: int = 0) -> dict[str, float] | None:
        """The newest heartbeat stats of ``robot`` that arrived after ``after_ns``."""
        for r, m, t in reversed(list(self.got)):
            if r == robot and isinstance(m, Heartbeat) and t > after_ns:
                return m.stats
        return None

    def first_heartbeat_after(self, robot: str, after_ns: int) -> int | None:
        for r, m, t in list(self.got):
            if r == robot and isinstance(m, Heartbeat) and t > after_ns:
                return t
        return None

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        self.sock.close(0)
        self.ctx.term()


class Commands:
    """The controller's operator process sending ``arm_stop`` at ``COMMAND_HZ``, counted."""

    def __init__(self, proc) -> None:
        self.proc = proc
        self.sent: list[int] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        period = 1.0 / COMMAND_HZ
        next_t = time.monotonic()
        while not self._stop.is_set():
            self.proc.send({"action": "arm_stop"})
            self.sent.append(now_ns())
            next_t += period
            self._stop.wait(max(0.0, next_t - time.monotonic()))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    fleet = Fleet(
        robots=list(ROBOTS),
        operators={
            "c2": "controller",
            "obs1": "observer",
            "obs2": "observer",
            "mallory": "observer",
            "rec": "recorder",
        },
        workdir=tmp_path_factory.mktemp("voice"),
    )
    with fleet:
        relay = fleet.start_relay()
        fleet.wait_for(lambda: "relay up" in relay.log_text(), 30, "the relay")
        for name in ROBOTS:
            fleet.start_robot(name, None)
        fleet.c2 = fleet.start_operator("c2", "cell2", want_frames=False)
        fleet.wire = Wire(fleet, "rec", (Heartbeat.TOPIC,))
        fleet.observers = [Wire(fleet, o, (TactileFrame.TOPIC,)) for o in ("obs1", "obs2")]
        fleet.commands = Commands(fleet.c2)
        try:
            fleet.wait_for(
                lambda: (
                    all(fleet.wire.robot_stats(r) for r in ROBOTS)
                    and (fleet.wire.robot_stats("cell2") or {}).get("commands_received", 0) > 10
                ),
                60,
                "both robots' heartbeats and cell2 hearing its controller",
            )
            yield fleet
        finally:
            fleet.commands.close()
            for w in (fleet.wire, *fleet.observers):
                w.close()


def _commands_through(fleet: Fleet, seconds: float) -> tuple[int, int, float]:
    """(commands sent, commands cell2 counted, stops it latched) over ``seconds`` from now.

    cell2's counters are read from its heartbeats at both ends of the window;
    the end reading is taken 0.5 s after the window so the last commands have
    arrived (the sent count covers exactly the window).
    """
    wire = fleet.wire
    t0 = now_ns()
    fleet.wait_for(lambda: wire.robot_stats("cell2", t0) is not None, 5, "a heartbeat of cell2")
    before = wire.robot_stats("cell2", t0)
    t_sent0 = now_ns()
    time.sleep(seconds)
    t_sent1 = now_ns()
    time.sleep(0.5)
    t1 = now_ns()
    fleet.wait_for(lambda: wire.robot_stats("cell2", t1) is not None, 5, "a heartbeat of cell2")
    after = wire.robot_stats("cell2", t1)
    sent = sum(1 for t in list(fleet.commands.sent) if t_sent0 <= t < t_sent1)
    received = after.get("commands_received", 0) - before.get("commands_received", 0)
    stops = after.get("arm_stops_latched", 0) - before.get("arm_stops_latched", 0)
    return sent, int(received), stops


def test_cell1s_key_cannot_unsubscribe_cell2_from_its_commands(fleet):
    ctx = zmq.Context()
    cell2_prefixes = [name_prefix(t, b"cell2") for t in (Command.TOPIC, Heartbeat.TOPIC)]
    cell2_prefixes.append(name_prefix(VideoSignal.TOPIC, b"cell2"))
    wrong = [*cell2_prefixes, b"", Command.TOPIC, name_prefix(Command.TOPIC, b"cell2")[:-1]]
    try:
        # a raw XSUB with cell1's robot key: subscribe and unsubscribe cell2's and everything;
        # with verbose unsubscribes its socket sends even what it never subscribed
        raw = _socket(ctx, fleet, zmq.XSUB, "cell1", fleet.robots_command)
        with contextlib.suppress(AttributeError, zmq.ZMQError):  # else: the pairs still go out
            raw.setsockopt(zmq.XSUB_VERBOSE_UNSUBSCRIBE, 1)
        time.sleep(0.3)  # the handshake
        for prefix in wrong:
            raw.send(b"\x00" + prefix)
            raw.send(b"\x01" + prefix)
            raw.send(b"\x00" + prefix)
        # an ordinary SUB with cell1's key asking for the wrong prefixes, then closing: libzmq
        # sends an unsubscribe for every prefix it asked for
        sub = _socket(ctx, fleet, zmq.SUB, "cell1", fleet.robots_command)
        for prefix in wrong:
            sub.setsockopt(zmq.SUBSCRIBE, prefix)
        time.sleep(0.3)
        sub.close(0)
        time.sleep(0.2)
        raw.close(0)
        time.sleep(0.3)  # the closed connections' unsubscribes reach the relay
    finally:
        ctx.term()
    sent, received, stops = _commands_through(fleet, AFTER_S)
    assert sent >= 0.9 * COMMAND_HZ * AFTER_S, f"the test sent only {sent} (a starved test)"
    assert received >= 0.9 * sent, f"cell2 counted {received} of {sent} commands after the attack"
    assert stops >= 0.9 * sent, f"cell2 latched {stops} of {sent} STOPs after the attack"
    print(f"after the attack cell2 counted {received} of {sent} commands, {stops:.0f} STOPs")


def test_an_observers_large_frames_reach_no_robot_and_cost_the_relay_nothing(fleet):
    relay = fleet.procs["relay"]
    pid = relay.popen.pid
    mallory_key = Path(fleet.members["mallory"].curve_public).read_text()
    idle_kb = _rss_kb(pid)
    ctx = zmq.Context()
    t0 = now_ns()
    peak_kb = idle_kb
    try:
        for size in (17 * 1024, 50 * 1024 * 1024):
            raw = _socket(ctx, fleet, zmq.XSUB, "mallory", fleet.ops_telemetry)
            time.sleep(1.1)  # the handshake, and the relay's log of endings ready for a line
            logged = len(relay.log_text())
            t_send = time.monotonic()
            raw.send(b"\x02" + b"x" * (size - 1))
            print(f"{size} bytes sent in {time.monotonic() - t_send:.2f} s")
            # a second of the relay's memory; for the large frame, until the relay has said
            # that it ended the connection (mallory still holds it open), however busy it is
            said = "subscriber connection ended at the relay (telemetry)"
            start = time.monotonic()
            while time.monotonic() < start + 1.0 or (
                size > 64 * 1024
                and said not in relay.log_text()[logged:]
                and time.monotonic() < start + LOG_WITHIN_S
            ):
                peak_kb = max(peak_kb, _rss_kb(pid))
                time.sleep(0.02)
            if size > 64 * 1024:
                ended = relay.log_text()[logged:]
                assert said in ended, f"nothing logged in {LOG_WITHIN_S:g} s: {ended!r}"
                assert "a key that had sent nothing from 127.0.0.1:" in ended, ended
            raw.close(0)
    finally:
        ctx.destroy(linger=0)  # a failed check leaves the 50 MB frame queued: never wait on it
    t_through = now_ns()
    time.sleep(AFTER_S)
    t_after = now_ns()
    peak_kb = max(peak_kb, _rss_kb(pid))
    through_s, after_s = (t_through - t0) / 1e9, (t_after - t_through) / 1e9
    counts = {
        (i, robot): (
            obs.count(robot, TactileFrame, t0, t_through),
            obs.count(robot, TactileFrame, t_through, t_after),
        )
        for i, obs in enumerate(fleet.observers)
        for robot in ROBOTS
    }
    print(f"frames through {through_s:.1f} s and after {after_s:.1f} s: {counts}")
    for obs in fleet.observers:
        for robot in ROBOTS:
            during = obs.count(robot, TactileFrame, t0, t_through)
            after = obs.count(robot, TactileFrame, t_through, t_after)
            # the frame grid's own rate, less 10 % and one frame for the window's edges
            assert during >= 0.9 * FRAME_HZ * through_s - 1, (robot, during, through_s)
            assert after >= 0.9 * FRAME_HZ * after_s - 1, (robot, after, after_s)
    for robot in ROBOTS:  # each robot's telemetry link never dropped (no reopen needed)
        stats = fleet.wire.robot_stats(robot, t_after - 1_000_000_000)
        assert stats is not None and stats.get("link_telemetry_reopened", 0) == 0, (robot, stats)
    assert peak_kb - idle_kb < 20 * 1024, f"relay RSS {idle_kb} -> {peak_kb} kB"
    fleet.wait_for(
        lambda: "frame from a subscriber dropped at the relay (telemetry)" in relay.log_text(),
        5,
        "the relay's log of the dropped frame",
    )
    text = relay.log_text()
    key = next(line.split('"')[1] for line in mallory_key.splitlines() if "public-key" in line)
    assert f"key {key}" in text and "sent 17408 bytes" in text, text[-2000:]
    print(f"relay RSS idle {idle_kb} kB, peak {peak_kb} kB")


def test_a_robot_whose_telemetry_link_hit_a_protocol_error_reconnects_within_2_s(fleet):
    """The relay's port answered once in a language the robot does not speak (a ZMTP greeting
    offering NULL to a CURVE client): libzmq gives up on that connection for good. The relay
    is back on its port: each robot is heard again within 2 s, by itself."""
    host, port = fleet.robots_telemetry.removeprefix("tcp://").split(":")
    fleet.stop("relay")
    greeting = b"\xff" + bytes(8) + b"\x7f" + b"\x03\x00" + b"NULL".ljust(20, b"\0") + bytes(32)
    refused: list[int] = []
    squatter = socket.socket()
    squatter.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    squatter.bind((host, int(port)))
    squatter.listen(8)
    squatter.settimeout(10)
    try:
        while len(refused) < len(ROBOTS):  # one connection of each robot's telemetry socket
            conn, _ = squatter.accept()
            conn.sendall(greeting)
            time.sleep(0.05)
            conn.close()
            refused.append(now_ns())
    finally:
        squatter.close()
    time.sleep(0.3)  # libzmq has ended both connections, for good without the robot's watch
    relay = fleet.start_relay()
    fleet.wait_for(lambda: "relay up" in relay.log_text(), 30, "the relay back")
    t_up = now_ns()
    for robot in ROBOTS:
        fleet.wait_for(
            lambda r=robot: fleet.wire.first_heartbeat_after(r, t_up) is not None,
            10,
            f"{robot}'s heartbeats through the relay again",
        )
        back_ms = (fleet.wire.first_heartbeat_after(robot, t_up) - t_up) / 1e6
        assert back_ms < 2000, f"{robot} heard {back_ms:.0f} ms after the relay was back"
        # its own view catches up with what the wire shows: within the same 2 s, a heartbeat
        # that says the link is up (the first through may still carry the socket's old state)
        fleet.wait_for(
            lambda r=robot: (fleet.wire.robot_stats(r, t_up) or {}).get("link_telemetry_up") == 1.0,
            max(0.0, 2.0 - (now_ns() - t_up) / 1e9),
            f"{robot}'s heartbeat saying its telemetry link is up",
        )
        stats = fleet.wire.robot_stats(robot, t_up)
        assert stats.get("link_telemetry_reopened", 0) >= 1, stats
        print(f"{robot} heard again {back_ms:.0f} ms after the relay was back")
    assert "opening the socket again" in fleet.procs["cell1"].log_text()
