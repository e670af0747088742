"""A Robotiq 2F that answers the URCap socket protocol on loopback.

``GripperSimServer`` serves a ``GripperModel`` (``robot_side.gripper.model``:
the registers, the fingers, the object) on TCP the way the URCap does on
port 63352; ``robot_side.gripper.rtu_sim`` serves the same model as Modbus
RTU on a pseudo-terminal. ``SimulatedGripper`` (kind "simulated") is the
real ``RobotiqSocketGripper`` connected to a server it starts in-process,
so node code is the same as on the robot.
"""

from __future__ import annotations

import contextlib
import logging
import socket
import threading
from dataclasses import dataclass
from typing import Any

from common.config.typed import param
from common.devices.lifecycle import OnItsSimulator, as_hardware
from common.errors import DeviceError
from robot_side.gripper.model import GripperModel, GripperModelConfig
from robot_side.gripper.urcap_socket import RobotiqSocketConfig, RobotiqSocketGripper

__all__ = [
    "GripperModel",
    "GripperModelConfig",
    "GripperSimConfig",
    "GripperSimServer",
    "SimulatedGripper",
    "SimulatedGripperConfig",
]

log = logging.getLogger(__name__)
wire_log = logging.getLogger("robot_side.gripper.sim.wire")


@dataclass
class GripperSimConfig:
    host: str = param("127.0.0.1", "loopback address to serve on (tests use 127.0.0.x)")
    port: int = param(0, "TCP port; 0 picks a free one (the real URCap uses 63352)")
    model: GripperModelConfig = param(GripperModelConfig(), "the simulated gripper")


class GripperSimServer:
    """The URCap socket server in front of a ``GripperModel``."""

    def __init__(self, config: GripperSimConfig | None = None) -> None:
        self.config = config or GripperSimConfig()
        self.model = GripperModel(self.config.model)
        self.host = self.config.host
        self.port = self.config.port
        self._listener: socket.socket | None = None
        self._conns: list[socket.socket] = []
        self._threads: list[threading.Thread] = []
        self._quit = threading.Event()
        self._mute = threading.Event()
        self._lock = threading.Lock()
        self.requests = 0

    def start(self) -> GripperSimServer:
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((self.config.host, self.config.port))
        except OSError as e:
            s.close()
            raise DeviceError(
                f"gripper simulator cannot bind {self.config.host}:{self.config.port} ({e}); "
                "use port 0 for a free one"
            ) from e
        s.listen(4)
        self._listener = s
        self.host, self.port = s.getsockname()[:2]
        self._quit.clear()
        for name, target in (("tick", self._tick_loop), ("accept", self._accept_loop)):
            t = threading.Thread(target=as_hardware(target), name=f"grippersim-{name}", daemon=True)
            self._threads.append(t)
            t.start()
        log.info("gripper simulator serving on %s:%d", self.host, self.port)
        return self

    def stop(self) -> None:
        """Close every socket: to a client, the gripper has vanished."""
        self._quit.set()
        self.unplug()
        for t in self._threads:
            t.join(timeout=2.0)
        self._threads.clear()

    def drop_connections(self) -> None:
        """Close the clients' connections but keep listening (a URCap restart)."""
        with self._lock:
            conns, self._conns = self._conns, []
        for c in conns:
            with contextlib.suppress(OSError):
                c.shutdown(socket.SHUT_RDWR)
            c.close()

    def unplug(self) -> None:
        """Pull the network cable: the port refuses connections and open ones close.

        The fingers keep their command (a real 2F-85 holds its grip when its
        link drops); ``replug`` listens on the same address again.
        """
        with self._lock:  # an accept in flight sees the cable gone (see _accept_loop)
            listener, self._listener = self._listener, None
        if listener is not None:
            with contextlib.suppress(OSError):
                listener.shutdown(socket.SHUT_RDWR)
            listener.close()
        self.drop_connections()
        if not self._quit.is_set():
            log.info("gripper simulator unplugged")

    def replug(self) -> None:
        """Listen again on the address it had: the driver's reconnect finds the same gripper."""
        if self._listener is not None:
            return
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind((self.host, self.port))
        s.listen(4)
        with self._lock:
            self._listener = s
        t = threading.Thread(
            target=as_hardware(self._accept_loop), name="grippersim-accept", daemon=True
        )
        self._threads.append(t)
        t.start()
        log.info("gripper simulator plugged in again on %s:%d", self.host, self.port)

    def mute(self, muted: bool = True) -> None:
        """Read requests but answer none (a hung URCap)."""
        if muted:
            self._mute.set()
        else:
            self._mute.clear()

    def stats(self) -> dict[str, Any]:
        with self._lock:
            clients = len(self._conns)
        return {"requests": self.requests, "clients": clients, **self.model.read()}

    def __enter__(self) -> GripperSimServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _tick_loop(self) -> None:
        self.model.run(self._quit)

    def _accept_loop(self) -> None:
        assert self._listener is not None
        listener = self._listener
        while not self._quit.is_set():
            try:
                conn, peer = listener.accept()
            except OSError:
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._lock:
                if self._listener is not listener:
                    # unplugged between accept() and here: drop_connections() could not see
                    # this one, and it would have served on with the cable out
                    conn.close()
                    return
                self._conns.append(conn)
            threading.Thread(
                target=self._serve, args=(conn, peer), name="grippersim-conn", daemon=True
            ).start()

    def _serve(self, conn: socket.socket, peer: Any) -> None:
        buf = b""
        try:
            while not self._quit.is_set():
                chunk = conn.recv(4096)
                if not chunk:
                    return
                buf += chunk
                while b"\n" in buf:
                    raw, _, buf = buf.partition(b"\n")
                    line = raw.decode(errors="replace").strip()
                    reply = self.handle(line)
                    wire_log.debug("%s <- %r -> %r", peer, line, reply)
                    if not self._mute.is_set():
                        conn.sendall(reply.encode() + b"\n")
        except OSError:
            pass
        finally:
            with self._lock:
                if conn in self._conns:
                    self._conns.remove(conn)
            conn.close()

    def handle(self, line: str) -> str:
        """One request line -> one reply line, as the URCap answers."""
        self.requests += 1
        parts = line.split()
        if len(parts) == 2 and parts[0] == "GET":
            values = self.model.read()
            if parts[1] in values:
                return f"{parts[1]} {values[parts[1]]}"
            return "?"
        if len(parts) >= 3 and parts[0] == "SET" and len(parts) % 2 == 1:
            try:
                pairs = {parts[i]: int(parts[i + 1]) for i in range(1, len(parts), 2)}
                self.model.write(**pairs)
            except (KeyError, ValueError):
                return "?"
            return "ack"
        return "?"


@dataclass
class SimulatedGripperConfig(RobotiqSocketConfig):
    host: str = param("127.0.0.1", "loopback address for the in-process simulator")
    port: int = param(0, "0 picks a free port; the driver then connects to it")
    sim: GripperModelConfig = param(GripperModelConfig(), "the simulated gripper and object")


class SimulatedGripper(OnItsSimulator, RobotiqSocketGripper):
    """The real socket driver against a simulator it starts on connect, stops on disconnect."""

    Config = SimulatedGripperConfig

    def __init__(self, config: SimulatedGripperConfig | None = None) -> None:
        super().__init__(config or SimulatedGripperConfig())
        self.server: GripperSimServer | None = None
        self._configured_port = self.config.port

    def _start_simulator(self) -> None:
        assert isinstance(self.config, SimulatedGripperConfig)
        if self.server is None:
            sim = GripperSimConfig(self.config.host, self.config.port, self.config.sim)
            self.server = GripperSimServer(sim).start()
        self.config.port = self.server.port

    def _stop_simulator(self) -> None:
        server, self.server = self.server, None
        if server is not None:
            server.stop()
            self.config.port = self._configured_port
