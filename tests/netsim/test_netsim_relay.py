"""The stream relay on raw TCP: every byte through unchanged, in order, late by the scenario."""

from __future__ import annotations

import random
import socket
import struct
import time

import pytest

from common.errors import ConfigError
from common.netsim.kernel_stamps import ANC_BYTES, SO_TIMESTAMPNS, arrival_ns, real_minus_mono_ns
from common.netsim.proxy import Endpoints
from common.netsim.scenario import scenario_from_dict
from common.netsim.stream import StreamForwarder


def _robot_listener() -> tuple[socket.socket, str]:
    server = socket.create_server(("127.0.0.1", 0))
    server.settimeout(5)
    return server, f"tcp://127.0.0.1:{server.getsockname()[1]}"


def _relay(scenario, robot_at: str) -> StreamForwarder:
    return StreamForwarder(
        scenario,
        endpoints=Endpoints(
            robot_telemetry=robot_at,
            robot_commands=robot_at,
            operator_telemetry="tcp://127.0.0.1:*",
            operator_commands="tcp://127.0.0.1:*",
        ),
        seed=5,
    )


def _connect(endpoint: str) -> socket.socket:
    host, port = endpoint[len("tcp://") :].rsplit(":", 1)
    s = socket.create_connection((host, int(port)), timeout=5)
    s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return s


def _read_exactly(sock: socket.socket, n: int) -> bytes:
    out = bytearray()
    while len(out) < n:
        chunk = sock.recv(n - len(out))
        if not chunk:
            break
        out += chunk
    return bytes(out)


def test_no_byte_reaches_the_robot_before_its_delay_by_the_kernels_clock():
    """Each 8-byte record is its send time; the robot's kernel stamps every read. The byte a
    read ends with left the relay no sooner than its record's send time plus the delay."""
    stamp = struct.Struct("!q")
    server, robot_at = _robot_listener()
    early_us: list[float] = []
    with server, _relay(scenario_from_dict({"both": {"delay_ms": 20.0}}), robot_at) as relay:
        operator = _connect(relay.operator_commands_endpoint)
        robot, _ = server.accept()
        robot.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        offset = real_minus_mono_ns()
        data = bytearray()
        reads: list[tuple[int, int]] = []  # (bytes so far, kernel receive time)

        def read(timeout_s: float) -> None:
            robot.settimeout(timeout_s)
            try:
                chunk, anc, _, _ = robot.recvmsg(4096, ANC_BYTES)
            except (BlockingIOError, TimeoutError):
                return
            assert chunk, "the relay closed the stream"
            data.extend(chunk)
            reads.append((len(data), arrival_ns(anc, time.monotonic_ns(), offset)))

        sent = 150
        for _ in range(sent):
            operator.sendall(stamp.pack(time.monotonic_ns()))
            read(0.002)  # read as the bytes come: one read each, mostly
        while len(data) < sent * stamp.size:
            read(2.0)
        operator.close()
        robot.close()
    for end, at in reads:
        (t_send,) = stamp.unpack_from(data, (end - 1) // stamp.size * stamp.size)
        if at - t_send < 20_000_000:
            early_us.append(round((20_000_000 - (at - t_send)) / 1000, 1))
    assert not early_us, f"{len(early_us)} of {len(reads)} reads came early, by {early_us} us"


def test_bytes_pass_unchanged_both_ways_with_delay_jitter_and_loss():
    scenario = scenario_from_dict(
        {
            "both": {
                "delay_ms": 5.0,
                "jitter_ms": 2.0,
                "distribution": "normal",
                "delay_correlation": 0.3,
                "loss_percent": 10.0,
                "retransmit_ms": 20.0,
            }
        }
    )
    server, robot_at = _robot_listener()
    rng = random.Random(1)
    up = bytes(rng.randrange(256) for _ in range(20_000))
    down = bytes(rng.randrange(256) for _ in range(20_000))
    with server, _relay(scenario, robot_at) as relay:
        operator = _connect(relay.operator_telemetry_endpoint)
        robot, _ = server.accept()
        robot.settimeout(5)
        t0 = time.monotonic()
        for i in range(0, len(up), 250):  # many chunks, each with its own fate
            operator.sendall(up[i : i + 250])
            robot.sendall(down[i : i + 250])
            time.sleep(0.002)
        assert _read_exactly(robot, len(up)) == up
        assert _read_exactly(operator, len(down)) == down
        assert time.monotonic() - t0 >= 0.005  # at least the base delay
        counts = relay.counters()
        assert counts["to_robot"]["retransmitted"] > 0  # losses became stalls, not gaps
        operator.close()
        robot.close()


def test_a_close_on_one_side_reaches_the_other():
    server, robot_at = _robot_listener()
    with server, _relay(scenario_from_dict({}), robot_at) as relay:
        operator = _connect(relay.operator_commands_endpoint)
        robot, _ = server.accept()
        robot.settimeout(5)
        operator.sendall(b"hello")
        assert _read_exactly(robot, 5) == b"hello"
        operator.close()
        assert robot.recv(10) == b""  # the relay passed the close on
        robot.close()


def test_datagram_scenarios_need_the_message_mode():
    with pytest.raises(ConfigError, match="message"):
        StreamForwarder(scenario_from_dict({"both": {"delivery": "datagram"}}))
