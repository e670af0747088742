"""CURVE: a stranger reads nothing and commands nothing; the wire carries no plaintext."""

from __future__ import annotations

import socket
import threading
import time

import pytest
import zmq
from tests_support import ProtocolOperator, RecordingArm, free_ports

from common.errors import LinkError
from common.keys.curve import SecurityConfig, check_endpoint, client_options
from common.wire.codec import encode
from common.wire.messages import Command, Stimulus
from common.wire.transport import Publisher, Subscriber
from robot_side.node import RobotNode
from robot_side.node.config import RobotConfig
from robot_side.tactile.scripted import ScriptedTactileSensor

pytestmark = pytest.mark.slow


class Relay:
    """A TCP relay that keeps every byte it forwards: what a wiretap would see."""

    def __init__(self, target_port: int) -> None:
        self.target = ("127.0.0.1", target_port)
        self.server = socket.create_server(("127.0.0.1", 0))
        self.port = self.server.getsockname()[1]
        self.captured = bytearray()
        self._lock = threading.Lock()
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self.server.accept()
            except OSError:
                return
            upstream = socket.create_connection(self.target)
            for a, b in ((client, upstream), (upstream, client)):
                threading.Thread(target=self._pump, args=(a, b), daemon=True).start()

    def _pump(self, src: socket.socket, dst: socket.socket) -> None:
        try:
            while data := src.recv(65536):
                with self._lock:
                    self.captured += data
                dst.sendall(data)
        except OSError:
            pass

    def close(self) -> None:
        self.server.close()


def _collect(sub: Subscriber, seconds: float) -> list:
    out, end = [], time.monotonic() + seconds
    while time.monotonic() < end:
        if sub.poll(0.05):
            out += [m for m, _ in sub.drain()]
    return out


def test_only_an_allowed_key_reads_the_stream_or_moves_the_arm(keys):
    tel, cmd = free_ports(2)
    rc = RobotConfig()
    rc.render.mode = "mask_ground_truth"
    rc.link.telemetry_endpoint = f"tcp://127.0.0.1:{tel}"
    rc.link.command_endpoint = f"tcp://127.0.0.1:{cmd}"
    rc.link.security = keys["robot"]
    arm = RecordingArm()
    robot = RobotNode(rc, ScriptedTactileSensor(), arm=arm)
    stop = threading.Event()
    thread = threading.Thread(target=robot.run, args=(stop,), daemon=True)
    thread.start()
    relay = Relay(tel)
    ctx = zmq.Context()
    try:
        time.sleep(0.3)
        jog = Command(seq=1, t_send_ns=1, action="arm_jog", velocity=(0.01, 0, 0, 0, 0, 0))
        # strangers: a wrong key, and no key at all
        for name, opts in (("stranger", client_options(keys["stranger"])), ("plain", {})):
            sub = Subscriber(ctx, f"tcp://127.0.0.1:{tel}", bind=False, sock_opts=opts)
            pub = Publisher(ctx, f"tcp://127.0.0.1:{cmd}", bind=False, sock_opts=opts)
            time.sleep(0.3)
            for _ in range(10):
                pub.send(jog)
                time.sleep(0.02)
            assert _collect(sub, 1.0) == [], f"{name} client read the stream"
            sub.close()
            pub.close()
        assert arm.jogs == [], "a client without an allowed key moved the arm"
        # the allowed operator, through the wiretap
        opts = client_options(keys["operator"])
        sub = Subscriber(ctx, f"tcp://127.0.0.1:{relay.port}", bind=False, sock_opts=opts)
        pub = Publisher(ctx, f"tcp://127.0.0.1:{cmd}", bind=False, sock_opts=opts)
        time.sleep(0.3)
        got = _collect(sub, 1.5)
        stimuli = [m for m in got if isinstance(m, Stimulus)]
        assert stimuli, "the allowed operator received no stimulus"
        operator = ProtocolOperator(sub, pub)
        operator.sync()  # the robot moves nothing before it knows the operator's clock
        for _ in range(10):
            operator.command("arm_jog", velocity=jog.velocity)
            operator.pump(0.02)
        deadline = time.monotonic() + 2
        while not arm.jogs and time.monotonic() < deadline:
            time.sleep(0.02)
        assert arm.jogs and arm.jogs[0] == jog.velocity
        sub.close()
        pub.close()
        wire = bytes(relay.captured)
        assert len(wire) > 1000
        for plain in (
            b"STIM",
            b"HBRT",
            b"stimulus",
            b"heartbeat",
            b"t_capture_ns",
            encode(stimuli[0])[4:20],
        ):
            assert plain not in wire, f"{plain!r} readable on the wire"
    finally:
        stop.set()
        thread.join(timeout=5)
        relay.close()
        ctx.destroy(linger=0)


def test_plain_tcp_off_this_machine_is_refused_unless_allowed():
    plain = SecurityConfig()
    check_endpoint("tcp://127.0.0.1:5555", plain)
    check_endpoint("tcp://localhost:5555", plain)
    check_endpoint("tcp://[::1]:5555", plain)
    for endpoint in ("tcp://*:5555", "tcp://192.0.2.7:5555", "tcp://robot.lab:5555"):
        with pytest.raises(LinkError, match="curve"):
            check_endpoint(endpoint, plain)
    check_endpoint("tcp://192.0.2.7:5555", SecurityConfig(allow_insecure=True))
