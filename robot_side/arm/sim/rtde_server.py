"""The RTDE server on 30004, protocol 2: recipes, start and pause, packages both ways.

Version negotiation, the controller version, output and input recipes (ids
numbered separately per connection), start and pause, data packages out at
each connection's requested frequency, and input packages into the control
script's registers. Variables come from the controller's table
(``rtde_wire``); unknown names are answered NOT_FOUND, inputs another live
connection owns IN_USE.
"""

from __future__ import annotations

import contextlib
import logging
import select
import socket
import struct
import threading
from typing import Any

from common.clocks.clock import now_s
from common.errors import DeviceError
from robot_side.arm.sim import rtde_wire as w
from robot_side.arm.sim.commands import STATUS_READY
from robot_side.arm.sim.controller import (
    ROBOT_MODE_RUNNING,
    SAFETY_MODE_PROTECTIVE_STOP,
    Controller,
)
from robot_side.arm.sim.script import ControlScript

log = logging.getLogger(__name__)
wire_log = logging.getLogger("robot_side.arm.sim.wire")

RUNTIME_STOPPED = 1
RUNTIME_PLAYING = 2
#: the control script's state register: ur-rtde sends a command only once it reads "ready" here
SCRIPT_STATE = "output_int_register_0"


def _names(payload: bytes) -> list[str]:
    """Recipe variable names; ur-rtde ends its list with a comma, the controller ignores it."""
    return [n for n in payload.decode(errors="replace").split(",") if n]


def register_value(script: ControlScript, name: str, rtde_type: str) -> Any:
    """A register's value as a data package carries it (zeros for what is not set)."""
    if name.startswith("output_int_register_"):
        return script.out_int.get(int(name.rsplit("_", 1)[1]), 0)
    if name.startswith("output_double_register_"):
        return script.out_double.get(int(name.rsplit("_", 1)[1]), 0.0)
    if name in script.inputs:
        return script.inputs[name]
    fmt = w.TYPE_FORMATS[rtde_type]
    if fmt.startswith("6"):
        return [0.0 if fmt.endswith("d") else 0] * 6
    if fmt.startswith("3"):
        return [0.0] * 3
    return False if fmt == "?" else (0.0 if fmt == "d" else 0)


class RTDEConnection:
    def __init__(self, sock: socket.socket, peer: Any) -> None:
        self.sock = sock
        self.peer = peer
        self.send_lock = threading.Lock()
        self.output_id = 0
        self.input_id = 0
        self.output: tuple[int, list[str], list[str], struct.Struct] | None = None
        self.output_period_s = 0.0  # one package per this many seconds (its frequency)
        self.next_package_s = 0.0  # monotonic s: when its next package is due
        self.last_package_s: float | None = None  # when its last package went out
        self.inputs: dict[int, tuple[list[str], list[str], struct.Struct]] = {}
        self.started = False
        self.alive = True
        #: bytes this connection's reader took off the socket and has not applied yet
        self.in_hand = False
        #: where the output recipe carries the script's state (None: it does not), and its value
        #: in the last package sent
        self.status_at: int | None = None
        self.status_sent: int | None = None

    def send(self, data: bytes) -> None:
        with self.send_lock:
            self.sock.sendall(data)

    def close(self) -> None:
        self.alive = False
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)
        with contextlib.suppress(OSError):
            self.sock.close()


class RTDEServer:
    """Every RTDE client's connection; what each asked for, and its data packages."""

    def __init__(
        self, controller: Controller, script: ControlScript, quit: threading.Event
    ) -> None:
        self.controller = controller
        self.config = controller.config
        self.script = script
        self._quit = quit
        self.conns: list[RTDEConnection] = []
        self.data_packages_sent = 0

    def serve(self, sock: socket.socket, peer: Any) -> None:
        """One RTDE client, until it goes or the controller does."""
        conn = RTDEConnection(sock, peer)
        with self.controller.lock:
            self.conns.append(conn)
        wire_log.debug("RTDE %s connected", peer)
        buf = b""
        try:
            while not self._quit.is_set():
                # Marked before it leaves the socket: recv() gives up the GIL, and the thread
                # that has taken the bytes waits for it back while the judging thread holds it,
                # which then saw neither bytes in the socket nor any in hand (a lab trial's
                # watchdog tripped at 103 ms of real silence in a 150 ms window).
                if not sock.recv(1, socket.MSG_PEEK):
                    break
                conn.in_hand = True  # arrived: the watchdog must not count it as missing
                chunk = sock.recv(65536)
                if not chunk:
                    break
                buf += chunk
                while len(buf) >= w.HEADER.size:
                    size, mtype = w.HEADER.unpack_from(buf)
                    if size < w.HEADER.size:
                        raise DeviceError(f"RTDE message size {size} is below the header size")
                    if len(buf) < size:
                        break
                    payload, buf = buf[w.HEADER.size : size], buf[size:]
                    self._handle(conn, mtype, payload)
                conn.in_hand = False  # what is left is part of a message still on its way
        except (OSError, DeviceError, struct.error) as e:
            if not self._quit.is_set():
                log.debug("RTDE %s dropped: %s", peer, e)
        finally:
            conn.close()
            with self.controller.lock:
                if conn in self.conns:
                    self.conns.remove(conn)
            wire_log.debug("RTDE %s disconnected", peer)

    def take_connections(self) -> list[RTDEConnection]:
        """Every connection, now no longer this server's (the controller vanishes)."""
        with self.controller.lock:
            conns, self.conns = self.conns, []
        return conns

    def client_count(self) -> int:
        """Connections still open; call with the controller's lock held."""
        return sum(1 for c in self.conns if c.alive)

    def _handle(self, conn: RTDEConnection, mtype: int, payload: bytes) -> None:
        if mtype not in (w.DATA_PACKAGE, w.SETUP_OUTPUTS, w.SETUP_INPUTS):
            wire_log.debug(
                "RTDE <- %s %s", w.MESSAGE_NAMES.get(mtype, mtype), payload[:200].hex(" ")
            )
        if mtype == w.REQUEST_PROTOCOL_VERSION:
            (version,) = struct.unpack(">H", payload[:2])
            self._reply(conn, mtype, bytes([1 if version in (1, 2) else 0]))
        elif mtype == w.GET_URCONTROL_VERSION:
            self._reply(conn, mtype, struct.pack(">IIII", *self.config.controller_version))
        elif mtype == w.SETUP_OUTPUTS:
            self._setup_outputs(conn, payload)
        elif mtype == w.SETUP_INPUTS:
            self._setup_inputs(conn, payload)
        elif mtype == w.START:
            conn.started = conn.output is not None or bool(conn.inputs)
            self._reply(conn, mtype, bytes([1 if conn.started else 0]))
        elif mtype == w.PAUSE:
            conn.started = False
            self._reply(conn, mtype, bytes([1]))
        elif mtype == w.DATA_PACKAGE:
            recipe_id = payload[0]
            recipe = conn.inputs.get(recipe_id)
            if recipe is None:
                log.warning("RTDE data package for unknown input recipe %d", recipe_id)
                return
            names, types, st = recipe
            values = w.unflatten(types, st.unpack(payload[1 : 1 + st.size]))
            with self.controller.lock:
                self.script.write_inputs(names, values)
        elif mtype == w.TEXT_MESSAGE:
            log.info("RTDE client message: %r", payload)
        else:
            log.warning("RTDE message type %d not understood", mtype)

    def _setup_outputs(self, conn: RTDEConnection, payload: bytes) -> None:
        mtype = w.SETUP_OUTPUTS
        (freq,) = struct.unpack(">d", payload[:8])
        names = _names(payload[8:])
        wire_log.debug("RTDE <- outputs at %.0f Hz: %s", freq, ",".join(names))
        types = [w.OUTPUT_TYPES.get(n, w.NOT_FOUND) for n in names]
        missing = [n for n, t in zip(names, types, strict=True) if t == w.NOT_FOUND]
        if missing:
            log.warning("RTDE client asked for outputs this simulator lacks: %s", missing)
            self._reply(conn, mtype, bytes([0]) + ",".join(types).encode())
            return
        conn.output_id += 1
        conn.output = (conn.output_id, names, types, w.recipe_struct(types))
        conn.status_at = names.index(SCRIPT_STATE) if SCRIPT_STATE in names else None
        freq = freq if freq > 0 else self.config.tick_hz
        conn.output_period_s = 1.0 / min(freq, self.config.tick_hz)
        self._reply(conn, mtype, bytes([conn.output_id]) + ",".join(types).encode())

    def _setup_inputs(self, conn: RTDEConnection, payload: bytes) -> None:
        mtype = w.SETUP_INPUTS
        names = _names(payload)
        wire_log.debug("RTDE <- inputs: %s", ",".join(names))
        types = [w.INPUT_TYPES.get(n, w.NOT_FOUND) for n in names]
        with self.controller.lock:
            taken = {
                n
                for c in self.conns
                if c is not conn and c.alive
                for ns, _, _ in c.inputs.values()
                for n in ns
            }
        types = [
            w.IN_USE if n in taken and t != w.NOT_FOUND else t
            for n, t in zip(names, types, strict=True)
        ]
        if any(t in (w.NOT_FOUND, w.IN_USE) for t in types):
            log.warning("RTDE input recipe refused: %s", dict(zip(names, types, strict=True)))
            self._reply(conn, mtype, bytes([0]) + ",".join(types).encode())
            return
        conn.input_id += 1
        conn.inputs[conn.input_id] = (names, types, w.recipe_struct(types))
        self._reply(conn, mtype, bytes([conn.input_id]) + ",".join(types).encode())

    def _reply(self, conn: RTDEConnection, mtype: int, payload: bytes) -> None:
        wire_log.debug("RTDE -> %s %s", w.MESSAGE_NAMES.get(mtype, mtype), payload[:200].hex(" "))
        conn.send(w.pack_message(mtype, payload))

    # -- data packages -------------------------------------------------------------

    def due(self) -> list[RTDEConnection]:
        """The connections a package is due to on this tick, each at its own frequency in
        wall time; call once per tick with the controller's lock held.

        By the clock, not by counting ticks: a controller sends at its rate whatever happens,
        and a tick this process ran late (a loaded machine) sends what is due at once. Counted
        in ticks, late ticks made every package of a stop's handshake late too, and the client
        waiting on them looked silent to the watchdog.
        """
        now = now_s()
        due = []
        for c in self.conns:
            if c.alive and c.started and c.output and now >= c.next_package_s:
                due.append(c)
                c.next_package_s += c.output_period_s
                if c.next_package_s <= now:  # behind by a period or more: from now on
                    c.next_package_s = now + c.output_period_s
        return due

    def status_owed(self) -> bool:
        """A client that writes inputs has not yet been sent the script's state as it is now.

        ur-rtde sends nothing, kicks included, until it reads the state it waits
        for ("ready", "done"); a controller publishes a change within a cycle. Here a
        starved cycle can publish it late, and the client's silence meanwhile is
        this controller's own. A hung script's state does not change, so a client
        waiting on one is still silent.
        """
        state = self.script.out_int.get(0, 0)
        return any(
            c.status_sent is not None and c.status_sent != state
            for c in self.conns
            if c.alive and c.inputs and c.status_at is not None
        )

    def writer_summary(self) -> str:
        """The command in the register, the script's state, and what the clients that write
        inputs last got from this controller (a trip's log)."""
        now, script = now_s(), self.script
        head = (
            f"command register {script.inputs.get('input_int_register_0', 0)}, script state "
            f"{script.out_int.get(0, 0)}"
        )
        parts = [
            f"{c.peer}: last package {(now - c.last_package_s) * 1000:.0f} ms ago, script "
            f"state sent {c.status_sent}"
            for c in self.conns
            if c.alive and c.inputs and c.last_package_s is not None
        ]
        return "; ".join([head, *parts])

    def writer_connected(self) -> bool:
        """A client that writes inputs is still connected (its socket not closed by its end)."""
        return any(not _closed_by_peer(c.sock) for c in self.conns if c.alive and c.inputs)

    def input_unread(self) -> bool:
        """A client that writes inputs has bytes this process has not applied yet.

        A real controller reads each package as it arrives; here the threads
        that read them can lag behind on a loaded machine, and an update that
        has arrived must not count as missing: neither bytes still in the
        socket, nor bytes its reader took off it and holds while it waits for
        the lock this judgement holds (the physics thread's ``advance``).
        """
        writers = [c for c in self.conns if c.alive and c.inputs]
        if any(c.in_hand for c in writers):
            return True
        socks = [c.sock for c in writers]
        try:
            readable, _, _ = select.select(socks, [], [], 0)
        except (OSError, ValueError):  # a socket closed meanwhile: judge on what was read
            return False
        return any(not _closed_by_peer(s) for s in readable)  # an end of file is no update

    def send(self, conn: RTDEConnection, state: dict[str, Any]) -> None:
        """One data package of ``state`` (and the registers) in ``conn``'s output recipe."""
        assert conn.output is not None
        rid, names, types, st = conn.output
        values = []
        for n, t in zip(names, types, strict=True):
            v = state.get(n)
            if v is None:
                v = register_value(self.script, n, t)
            values.append(v)
        try:
            conn.send(w.pack_message(w.DATA_PACKAGE, bytes([rid]) + st.pack(*w.flatten(values))))
            self.data_packages_sent += 1
            conn.last_package_s = now_s()
        except (OSError, struct.error) as e:
            log.debug("RTDE data to %s failed: %s", conn.peer, e)
            conn.close()
            return
        if conn.status_at is not None:
            status = values[conn.status_at]
            if status == STATUS_READY and conn.status_sent != STATUS_READY:
                with self.controller.lock:
                    self.script.client_may_send()
            conn.status_sent = status

    def state(self) -> dict[str, Any]:
        """What a data package reports, by output name; call with the controller's lock held."""
        controller = self.controller
        arm = controller.arm
        pose = arm.current_pose().tolist()
        speed = arm.velocity.tolist()
        q = arm.q.tolist()
        qd = arm.qd.tolist()
        safety = controller.safety_mode
        running = self.script.program_running
        status_bits = (1 if controller.powered else 0) | (2 if running else 0)
        return {
            "timestamp": controller.timestamp(),
            "actual_q": q,
            "target_q": q,
            "actual_qd": qd,
            "target_qd": qd,
            "actual_TCP_pose": pose,
            "target_TCP_pose": pose,
            "actual_TCP_speed": speed,
            "target_TCP_speed": speed,
            "robot_mode": ROBOT_MODE_RUNNING if controller.powered else 3,
            "joint_mode": [253] * 6,
            "safety_mode": safety,
            "safety_status": safety,
            "speed_scaling": 1.0,
            "target_speed_fraction": 1.0,
            "runtime_state": RUNTIME_PLAYING if running else RUNTIME_STOPPED,
            "robot_status_bits": status_bits,
            "safety_status_bits": (4 if safety == SAFETY_MODE_PROTECTIVE_STOP else 1),
            "actual_main_voltage": 48.0,
            "actual_robot_voltage": 48.0,
            "actual_robot_current": 0.8,
            "actual_joint_voltage": [48.0] * 6,
            "joint_temperatures": [32.0] * 6,
            "actual_execution_time": 0.2,
            "tool_temperature": 30.0,
            "tool_output_voltage": 24,
        }


def _closed_by_peer(sock: socket.socket) -> bool:
    """The other end closed ``sock`` (or it failed): what is left to read is its end of file.

    Never waits: a socket with nothing to read is open, and one that is readable answers a
    peek at once (a socket timeout would otherwise make the peek wait for data).
    """
    try:
        readable, _, _ = select.select([sock], [], [], 0)
        return bool(readable) and sock.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT) == b""
    except (BlockingIOError, InterruptedError):
        return False  # open, nothing to read
    except (OSError, ValueError):  # failed, or closed here meanwhile
        return True
