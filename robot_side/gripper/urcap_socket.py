"""Robotiq 2F through the Robotiq URCap's ASCII socket on the UR controller (port 63352).

The protocol is one line per request, one line per reply::

    SET POS 120 SPE 255 FOR 150 GTO 1\\n   ->  ack\\n
    GET POS\\n                              ->  POS 118\\n

Variables: ACT (activate), GTO (go to), ATR (auto-release), POS (request
when set, actual position when read), SPE, FOR, STA (activation status),
OBJ (object detection), FLT (fault), PRE (echo of the requested position).

Replies come in order on one connection, so a reply that misses its deadline
would be read as the answer to the next request: after any timeout or
malformed reply the connection is closed and the caller must ``connect()``
again, instead of trusting a stream that may be out of step.
"""

from __future__ import annotations

import logging
import socket
import threading
from dataclasses import dataclass

from common.config.typed import param
from common.devices.preflight import Finding, PreflightContext, tcp_findings
from common.errors import (
    DeviceAlreadyConnectedError,
    DeviceNotConnectedError,
    DeviceTimeoutError,
    ProtocolError,
)
from robot_side.gripper.base import GripLevels, Gripper, GripperState

log = logging.getLogger(__name__)

DEFAULT_PORT = 63352
STATE_VARIABLES = ("STA", "GTO", "OBJ", "FLT", "PRE", "POS")


@dataclass
class RobotiqSocketConfig:
    host: str = param("192.168.1.10", "the UR controller running the Robotiq URCap")
    port: int = param(DEFAULT_PORT, "the URCap's gripper socket (fixed by Robotiq)")
    connect_timeout_s: float = param(2.0, "TCP connect deadline: a dead host fails fast")
    reply_timeout_s: float = param(1.0, "per-request deadline; the URCap answers in a few ms")
    activation_timeout_s: float = param(5.0, "activation takes about 1.5 s on a 2F-85")
    activate_on_connect: bool = param(
        True, "activate at connect if not active (an inactive gripper refuses every move)"
    )
    levels: GripLevels = param(GripLevels(), "grip level 1..31 -> position and force")


class RobotiqSocketGripper(Gripper):
    Config = RobotiqSocketConfig

    def __init__(self, config: RobotiqSocketConfig | None = None) -> None:
        self.config = config or RobotiqSocketConfig()
        super().__init__(self.config.levels, self.config.activation_timeout_s)
        self._sock: socket.socket | None = None
        self._buf = b""
        self._io_lock = threading.Lock()
        self.requests = 0

    @property
    def where(self) -> str:
        return f"{self.config.host}:{self.config.port}"

    def _preflight(self, context: PreflightContext) -> list[Finding]:
        hint = "the Robotiq URCap must be installed and the gripper activated"
        return tcp_findings(self.config.host, [self.config.port], context, hint)

    def _location(self) -> str:
        return f"at {self.config.host} ports {[self.config.port]}"

    # -- lifecycle -----------------------------------------------------------

    @property
    def is_connected(self) -> bool:
        return self._sock is not None

    def connect(self) -> None:
        if self._sock is not None:
            raise DeviceAlreadyConnectedError(f"gripper at {self.where} is already connected")
        try:
            sock = socket.create_connection(
                (self.config.host, self.config.port), timeout=self.config.connect_timeout_s
            )
        except OSError as e:
            raise DeviceNotConnectedError(
                f"gripper: cannot reach the Robotiq URCap at {self.where} ({e}); check that "
                "the UR controller is on and the Robotiq Grippers URCap is installed"
            ) from e
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.settimeout(self.config.reply_timeout_s)
        self._sock, self._buf = sock, b""
        log.info("gripper connected to %s", self.where)
        if self.config.activate_on_connect:
            try:
                self.activate()
            except Exception:
                self.disconnect()
                raise

    def disconnect(self) -> None:
        sock, self._sock = self._sock, None
        if sock is not None:
            try:
                sock.close()
            finally:
                log.info("gripper disconnected from %s", self.where)

    # -- wire ----------------------------------------------------------------

    def _request(self, line: str) -> str:
        """One request, one reply line; any failure closes the connection."""
        with self._io_lock:
            sock = self._sock
            if sock is None:
                raise DeviceNotConnectedError(
                    f"gripper at {self.where} is not connected: call connect() first"
                )
            try:
                sock.sendall(line.encode() + b"\n")
                while b"\n" not in self._buf:
                    chunk = sock.recv(4096)
                    if not chunk:
                        raise ConnectionResetError("the URCap closed the connection")
                    self._buf += chunk
            except TimeoutError:
                self._drop()
                raise DeviceTimeoutError(
                    f"gripper at {self.where} did not answer {line!r} in "
                    f"{self.config.reply_timeout_s:.1f} s; connection closed. Check the URCap "
                    "on the pendant, then connect() again"
                ) from None
            except OSError as e:
                self._drop()
                raise DeviceNotConnectedError(
                    f"gripper at {self.where}: connection lost during {line!r} ({e}); "
                    "connect() again once the controller is back"
                ) from e
            reply, _, self._buf = self._buf.partition(b"\n")
            self.requests += 1
            return reply.decode(errors="replace").strip()

    def _drop(self) -> None:
        sock, self._sock = self._sock, None
        if sock is not None:
            sock.close()

    def _set(self, **values: int) -> None:
        line = "SET " + " ".join(f"{k} {v}" for k, v in values.items())
        reply = self._request(line)
        if reply != "ack":
            self._drop_protocol(line, reply)

    def _get(self, var: str) -> int:
        reply = self._request(f"GET {var}")
        name, _, value = reply.partition(" ")
        if name != var or not value.strip().lstrip("-").isdigit():
            self._drop_protocol(f"GET {var}", reply)
        return int(value)

    def _drop_protocol(self, sent: str, reply: str) -> None:
        with self._io_lock:
            self._drop()
        raise ProtocolError(
            f"gripper at {self.where} answered {reply!r} to {sent!r}; connection closed. "
            "Is port 63352 really the Robotiq URCap?"
        )

    # -- Gripper hooks -------------------------------------------------------

    def _write_activate(self) -> None:
        # rACT must go 0 -> 1; ATR 0 so no automatic release is pending
        self._set(ACT=0, ATR=0)
        self._set(ACT=1)

    def _write_command(self, position: int, speed: int, force: int, go: bool) -> None:
        # GTO last: the gripper moves on the values already set
        self._set(POS=position, SPE=speed, FOR=force, GTO=1 if go else 0)

    def _read_state(self) -> GripperState:
        v = {name: self._get(name) for name in STATE_VARIABLES}
        return GripperState(
            activation=v["STA"],
            goto=bool(v["GTO"]),
            object_status=v["OBJ"],
            fault=v["FLT"],
            requested_position=v["PRE"],
            position=v["POS"],
        )

    def position(self) -> int:
        self.require_connected()
        return self._get("POS")

    def object_detected(self) -> bool:
        self.require_connected()
        return self._get("OBJ") in (1, 2)

    def status(self) -> dict[str, object]:
        out = super().status()
        out.update(where=self.where, requests=self.requests)
        return out
