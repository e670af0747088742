"""Small test doubles and helpers shared by the system tests."""

from __future__ import annotations

import contextlib
import importlib.util
import json
import os
import signal
import socket
import subprocess
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from common.wire.codec import field_names
from common.wire.codec_schema import WIRE_KEYS
from common.wire.messages import Stimulus
from common.wire.transport import free_loopback_ports
from robot_side.arm.base import ArmLimits


def needs(module: str, reason: str | None = None) -> pytest.MarkDecorator:
    """Skip where ``module`` (an extra's library) is not installed, without importing it.

    ``pytest.importorskip`` at a module's top imports the library while every
    test worker collects every module: torch alone cost each worker about 2 s
    of CPU before any test ran. The tests import what they use when they run.
    """
    missing = importlib.util.find_spec(module.split(".")[0]) is None
    return pytest.mark.skipif(missing, reason=reason or f"needs {module}")


def readable(data: bytes, start: int = 4) -> dict:
    """A frame's msgpack map with its fields' names as keys (as docs/protocol.md names them)."""
    import msgpack

    return field_names(msgpack.unpackb(data[start:], raw=False))


def on_the_wire(topic: bytes, body: dict) -> bytes:
    """``body`` (fields by name) framed as its ``v`` spells it: version 1 by name, any other
    version with the one-character keys of version 2 (``WIRE_KEYS``)."""
    import msgpack

    if body.get("v") != 1:
        body = {WIRE_KEYS.get(k, k): v for k, v in body.items()}
    return topic + msgpack.packb(body, use_bin_type=True)


def free_ports(n: int) -> list[int]:
    """Ports free now, for this process's own sockets (a node in a thread here): a process
    of its own binds port 0 and says what it got (``ROBOT_BINDS_ITS_PORTS``)."""
    return free_loopback_ports(n)


#: a robot's ``--set`` arguments for a direct link on ports it binds itself (port 0); its
#: READY=1 says them (``Ready.endpoints``: telemetry, commands), ``link_to`` passes them on
ROBOT_BINDS_ITS_PORTS = [
    *("--set", 'link.telemetry_endpoint="tcp://127.0.0.1:0"'),
    *("--set", 'link.command_endpoint="tcp://127.0.0.1:0"'),
]


def link_to(endpoints: dict[str, str], section: str = "link") -> list[str]:
    """``--set`` arguments pointing a node's ``section`` at the ends a robot said it bound."""
    return [
        *("--set", f'{section}.telemetry_endpoint="{endpoints["telemetry"]}"'),
        *("--set", f'{section}.command_endpoint="{endpoints["commands"]}"'),
    ]


@contextlib.contextmanager
def unanswered_ports(n: int) -> Iterator[list[int]]:
    """``n`` loopback TCP ports this process holds bound and listening, never answered:
    where a node in another process connects to a robot that is not there. Held, they
    cannot be taken by anyone else (a port merely free when picked could)."""
    socks = [socket.create_server(("127.0.0.1", 0)) for _ in range(n)]
    try:
        yield [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()


class RecordingArm:
    """Stands in for the arm where a test only needs to know what it was told.

    It has the interface's ``limits`` (the node reads them, for the assist's box).
    """

    def __init__(self) -> None:
        self.limits = ArmLimits()
        self.jogs: list[tuple[float, ...]] = []
        self.jog_times: list[int] = []
        self.stop_times: list[int] = []
        self.is_connected = True

    def connect(self) -> None:
        self.is_connected = True

    def disconnect(self) -> None:
        self.is_connected = False

    def jog(self, velocity, issued_at_s=None):
        self.jogs.append(tuple(velocity))
        self.jog_times.append(time.monotonic_ns())
        return velocity

    def stop(self) -> None:
        self.stop_times.append(time.monotonic_ns())

    @property
    def stops(self) -> int:
        return len(self.stop_times)


class ProtocolOperator:
    """An operator as docs/protocol.md describes it, on raw sockets: heartbeats that echo the
    robot's, and commands stamped with a session, an increasing seq and the send time; each
    echoes the robot run it heard (``echo_session``), as the robot's replay window asks.

    The robot acts on motion commands only once a heartbeat round trip has given it the
    clock offset; ``sync()`` exchanges heartbeats until it has.
    """

    def __init__(self, sub, pub, session: int = 7) -> None:
        self.sub, self.pub = sub, pub  # common.wire.transport Subscriber / Publisher
        self.session = session
        self.seq = 0
        self.hb_seq = 0
        self.received: list = []  # (local receive ns, message)
        self._echo: tuple[int | None, int | None] = (None, None)
        self._next_hb_ns = 0
        self._echoing_sent: set[int] = set()  # our heartbeats that carried an echo
        self.robot_session: int | None = None  # the robot run we heard, echoed as the node does
        self.robot_has_clock = False  # the robot answered one of those: it knows our offset
        self.sent_ns: list[int] = []  # when each heartbeat and command went out (our clock)
        self.woke_ns: list[int] = []  # each turn of ``pump`` (at most 10 ms apart unless starved)

    def pump(self, duration_s: float = 0.0) -> None:
        """Read telemetry and keep heartbeats going (20 Hz) for ``duration_s``."""
        from common.clocks.clock import now_ns
        from common.wire.messages import Heartbeat

        end = now_ns() + round(duration_s * 1e9)
        while True:
            for msg, t_recv in self.sub.drain():
                self.received.append((t_recv, msg))
                if isinstance(msg, Heartbeat):
                    self._echo = (msg.t_send_ns, t_recv)
                    self.robot_session = msg.session
                    if msg.echo_t_send_ns in self._echoing_sent:
                        self.robot_has_clock = True
            now = now_ns()
            self.woke_ns.append(now)
            if now >= self._next_hb_ns:
                self.hb_seq += 1
                self.pub.send(
                    Heartbeat(
                        seq=self.hb_seq,
                        t_send_ns=now,
                        node="operator",
                        state="ok",
                        echo_t_send_ns=self._echo[0],
                        echo_t_recv_ns=self._echo[1],
                        session=self.session,
                        echo_session=self.robot_session,
                    )
                )
                self.sent_ns.append(now)
                if self._echo[0] is not None:
                    self._echoing_sent.add(now)
                self._next_hb_ns = now + 50_000_000
            if now >= end:
                return
            self.sub.poll(min(0.01, (end - now) / 1e9))

    def sync(self, timeout_s: float = 15.0) -> None:
        """Until the robot has taken a clock sample from our echoes (it echoed one back).

        A fixed wait was enough on a quiet machine; on a busy one the first
        commands then arrived unsynced and were refused.
        """
        deadline = time.monotonic() + timeout_s
        self.pump(0.35)
        while not self.robot_has_clock:
            if time.monotonic() > deadline:
                raise TimeoutError(f"the robot never echoed our heartbeats in {timeout_s:.0f} s")
            self.pump(0.05)
        self.pump(0.1)  # a few more samples for its offset filter

    def command(self, action: str, **fields):
        from common.clocks.clock import now_ns
        from common.wire.messages import Command

        self.seq += 1
        cmd = Command(
            seq=self.seq,
            t_send_ns=now_ns(),
            action=action,
            session=self.session,
            echo_session=self.robot_session,
            **fields,
        )
        self.pub.send(cmd)
        self.sent_ns.append(cmd.t_send_ns)
        return cmd


class DashboardDemo:
    """``deepxpalm demo --dashboard --json`` as a user runs it (a unit of the catalogue).

    ``with`` starts it and returns once the demo said READY=1 (every process of it up) with
    its page's address; the page's token is one given to it. ``finish()`` ends it with
    Ctrl-C, as a user does, and returns (exit code, the JSON summary or None, stderr).
    """

    def __init__(self, *args: str, duration_s: float = 120.0, ready_timeout_s: float = 90.0):
        from common.web.web_token import new_token
        from deploy.units.service import Service

        self.token = new_token()
        argv = ["demo", "--dashboard", "--json", *args, "--duration", str(duration_s)]
        argv += ["--set", "operator.dashboard.port=0"]  # a free one, said when ready
        argv += ["--set", f'operator.dashboard.token="{self.token}"']
        self.ready_timeout_s = ready_timeout_s
        self._stderr = tempfile.NamedTemporaryFile(prefix="deepxpalm-demo-", suffix=".log")  # noqa: SIM115
        self.service = Service(
            "demo", argv, Path(self._stderr.name), stdout=subprocess.PIPE, text=True
        )
        self.port = 0
        #: the page's address with its token
        self.url = ""

    @property
    def proc(self) -> subprocess.Popen | None:
        return self.service.popen

    @property
    def ws_url(self) -> str:
        """The page's WebSocket, with its token."""
        from common.web.web_token import with_token

        return with_token(f"ws://127.0.0.1:{self.port}/ws", self.token)

    def __enter__(self) -> DashboardDemo:
        from common.web.web_token import with_token
        from deploy.units.readiness import NotReady

        self.service.start()
        try:
            base = self.service.wait_ready(self.ready_timeout_s).endpoints["dashboard"]
        except NotReady as e:
            self.service.stop(0)
            # with --json the demo's account of why (its errors, each child's log) is on stdout
            summary = self.proc.stdout.read() if self.proc.stdout else ""
            self.service.close()
            raise RuntimeError(
                f"the demo never named its dashboard: {e}\nits summary: {summary[-4000:]}"
            ) from None
        self.port = int(base.rstrip("/").rpartition(":")[2])
        self.url = with_token(base, self.token)
        return self

    def stderr(self) -> str:
        return self.service.log_text()

    def finish(self, timeout_s: float = 60.0) -> tuple[int, dict | None, str]:
        self.proc.send_signal(signal.SIGINT)  # Ctrl-C, as a user ends it
        stdout, _ = self.proc.communicate(timeout=timeout_s)
        summary = json.loads(stdout) if stdout.strip() else None
        return self.proc.returncode, summary, self.stderr()

    def __exit__(self, exc_type: object, exc: BaseException | None, tb: object) -> None:
        if self.proc is None:
            return
        alive = self.proc.poll() is None
        self.service.stop(0)
        if exc is not None:
            # the test failed: what the demo said is the only account of why
            try:
                stdout, _ = self.proc.communicate(timeout=10)
            except (subprocess.TimeoutExpired, ValueError):
                stdout = ""
            exc.add_note(
                f"the demo {'was still running' if alive else 'had exited'} "
                f"(exit {self.proc.returncode}); its stdout:\n{(stdout or '')[-3000:]}\n"
                f"its stderr:\n{self.stderr()[-3000:]}"
            )
        self.service.close()


class VideoServerProcess:
    """``deepxpalm video`` on the test pattern as its own process (a unit of the catalogue),
    so its crash is seen from outside; ``with`` starts it and returns once it said READY=1
    with where it serves (``url``, its token from its token file; ``port``: its own choice
    unless given, as a restart's). Its log goes to a file (``log_text()``)."""

    def __init__(self, port: int | None = None, *settings: str) -> None:
        from deploy.units.service import Service

        self._dir = tempfile.TemporaryDirectory(prefix="deepxpalm-video-")
        named = [s.split("=", 1)[1].strip('"') for s in settings if s.startswith("token_file=")]
        self.token_file = Path(named[0]) if named else Path(self._dir.name) / "video.token"
        if not named:
            settings = (*settings, f'token_file="{self.token_file}"')
        self.port = port or 0
        argv = ["video", "--set", f"port={self.port}", *(a for s in settings for a in ("--set", s))]
        self.service = Service("video", argv, Path(self._dir.name) / "video.log", watchdog=False)
        #: its signalling URL with the token
        self.url = ""

    @property
    def proc(self) -> subprocess.Popen | None:
        return self.service.popen

    def log_text(self) -> str:
        """What the server logged so far."""
        return self.service.log_text()

    def __enter__(self) -> VideoServerProcess:
        from common.web.web_token import token_file, with_token
        from deploy.units.readiness import NotReady

        try:
            base = self.service.up(60).endpoints["signalling"]
        except NotReady as e:
            raise RuntimeError(f"the video server did not start: {e}") from None
        self.port = int(base.rstrip("/").rpartition(":")[2])
        self.url = with_token(base, token_file(self.token_file, "video token_file"))
        return self

    def __exit__(self, *exc: object) -> None:
        self.service.stop(0)  # SIGKILL: what it does on a stop is the tests' own business
        self.service.close()


def child_processes(parent_pid: int) -> dict[str, int]:
    """The pids of a ``deepxpalm demo``'s children by role, read from /proc, as ``ps`` would.

    Roles: the ``deepxpalm`` subcommand (robot, netsim, video, operator, router), ``servos``
    for the servo bus simulator, or ``world`` for the lab (``deepxpalm sim world``).
    """
    import os

    found: dict[str, int] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                ppid = int(f.read().rsplit(")", 1)[1].split()[1])
            with open(f"/proc/{entry}/cmdline", "rb") as f:
                words = f.read().decode(errors="replace").split("\0")
        except (OSError, ValueError, IndexError):
            continue  # gone meanwhile
        if ppid != parent_pid:
            continue
        for role in ("robot", "netsim", "video", "operator", "servos", "world", "router"):
            if role in words:
                found[role] = int(entry)
    return found


def listening_sockets(pid: int) -> list[tuple[str, str, int]]:
    """(protocol, address, port) of every socket process ``pid`` listens on, as ``ss -lnpt``
    and ``ss -lnpu`` list them: TCP in LISTEN, UDP unconnected; read from /proc."""
    import ipaddress
    import os
    import socket
    import struct

    inodes = set()
    for fd in os.listdir(f"/proc/{pid}/fd"):
        try:
            target = os.readlink(f"/proc/{pid}/fd/{fd}")
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    found = []
    for proto, listening in (("tcp", "0A"), ("tcp6", "0A"), ("udp", "07"), ("udp6", "07")):
        with open(f"/proc/{pid}/net/{proto}") as f:
            rows = [line.split() for line in f.readlines()[1:]]
        for row in rows:
            if row[9] not in inodes or row[3] != listening:
                continue
            hex_addr, hex_port = row[1].split(":")
            raw = bytes.fromhex(hex_addr)
            # /proc prints each 32-bit word in host order
            words = struct.unpack(f"<{len(raw) // 4}I", raw)
            packed = struct.pack(f">{len(words)}I", *words)
            family = socket.AF_INET if len(packed) == 4 else socket.AF_INET6
            address = str(ipaddress.ip_address(socket.inet_ntop(family, packed)))
            found.append((proto, address, int(hex_port, 16)))
    return found


class ManualClock:
    """A clock a test moves by hand: call it for the time (s), set or add to ``t``."""

    def __init__(self, t: float = 100.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def fifo_granted() -> bool:
    """Whether this process may run a thread at SCHED_FIFO (root, LimitRTPRIO=): tried on a
    thread of its own, which then ends."""
    import threading

    from common.process.realtime import raise_this_thread

    got: list = []
    t = threading.Thread(target=lambda: got.append(raise_this_thread(1, 0)))
    t.start()
    t.join()
    return got[0].realtime


def wait_until(cond: Callable[[], bool], timeout_s: float, period_s: float = 0.002) -> bool:
    """Poll ``cond`` until it holds or ``timeout_s`` passes; its last answer."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(period_s)
    return cond()


def stderr_on_pty(
    argv: list[str], env: dict[str, str], cwd: str | os.PathLike | None = None, timeout_s=240.0
) -> tuple[bytes, int]:
    """``argv`` with its stderr on a pseudo-terminal (a user's terminal): the bytes it wrote
    there, and its exit status. stdin and stdout are not the terminal."""
    import select

    master, slave = os.openpty()
    proc = subprocess.Popen(
        argv, cwd=cwd, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=slave
    )
    os.close(slave)
    seen = b""
    deadline = time.monotonic() + timeout_s
    try:
        while time.monotonic() < deadline:
            ready, _, _ = select.select([master], [], [], 0.5)
            if ready:
                try:
                    chunk = os.read(master, 65536)
                except OSError:  # EIO: the last holder of the slave exited
                    break
                if not chunk:
                    break
                seen += chunk
            elif proc.poll() is not None:
                break
        rc = proc.wait(timeout=max(deadline - time.monotonic(), 1.0))
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        os.close(master)
    return seen, rc


def stimulus(**kw) -> Stimulus:
    """A valid stimulus message; any field overridden by keyword."""
    import numpy as np

    base = dict(
        seq=7,
        t_send_ns=1_000,
        t_capture_ns=900,
        frame_seq=3,
        mode="mask",
        contact=True,
        stimulus=np.array([[0, 2.5, 0], [1.25, 0, 0], [0, 0, 0]], np.float32),
        pattern=4,
        confidence=0.93,
        grip_level=12,
    )
    base.update(kw)
    return Stimulus(**base)


def why_the_demo_failed(proc: subprocess.CompletedProcess) -> str:
    """A finished ``deepxpalm demo --json``'s exit code, the errors and process events of its
    summary (where it printed one), and the end of its stderr: what a failing test shows."""
    out = f"the demo exited with {proc.returncode}"
    start = 0 if proc.stdout.startswith("{") else proc.stdout.find("\n{")
    try:
        report = json.loads(proc.stdout[start:])
        out += f"\nerrors: {report['errors']}\nevents: {report['processes']['events']}"
        out += f"\nlogs: {report.get('logs')}"
    except (ValueError, KeyError, TypeError):
        out += f"\nstdout: {proc.stdout[-1500:]}"
    return f"{out}\nstderr: {proc.stderr[-3000:]}"
