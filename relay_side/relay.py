"""The relay: ZeroMQ's own proxy between sites that both connect out to it.

Robot nodes and operator nodes connect *out* to the relay, so neither site
opens an inbound port. Two paths:

- **telemetry** (robots -> operators): ``zmq.proxy_steerable`` from an XSUB
  (robots connect their XPUB) to an XPUB (operators connect their SUB). The
  relay never decodes it. Routing is ZeroMQ's prefix subscription on the
  topic and robot name (docs/protocol.md, Robot names); the subscriptions flow
  back through the proxy, so a robot sees what anyone asks for and skips raw
  frames nobody wants. A subscriber that stops reading fills only its own
  queue (``SNDHWM`` plus the kernel buffer) and is then dropped from: an XPUB
  never blocks on one peer (``XPUB_NODROP`` off).
- **commands** (operators -> robots): the same XSUB -> XPUB pair, but carried
  by a small loop instead of the proxy, because the relay enforces roles
  here: with CURVE each message arrives with its sender's key (ZAP
  ``User-Id``) and a ``CMND`` from a key whose roster role is not
  ``controller`` is dropped and counted, except an ``arm_stop`` from a role
  that may stop (``STOP_ROLES``: an observer may press STOP; the robot
  checks the signer's role again). Commands are low-rate (tens a second),
  so a Python loop costs nothing measurable.

The relay holds no key that can command a robot: commands are signed by the
operator (common/signing.py) and the robot checks them against its own
roster, so a compromised relay can delay or drop, never command
(docs/security.md).
"""

from __future__ import annotations

import logging
import struct
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

import msgpack
import zmq

from common.codec import MAX_MESSAGE_BYTES, MAX_NAME_LEN, TOPIC_LEN, DecodeError, split_name
from common.errors import ConfigError
from common.logs import BurstLog
from common.messages import STOP_ROLES
from common.roster import Roster, load_roster
from common.security import SecurityConfig, check_endpoint, server_options
from relay_side.config import RelayConfig

log = logging.getLogger(__name__)

#: ZAP domains: a robot key cannot pose as an operator, nor the reverse
ROBOTS_DOMAIN, OPERATORS_DOMAIN = "robots", "operators"
#: the counters libzmq's steerable proxy reports, in its order
PROXY_STAT_NAMES = (
    "frontend_msgs_in",
    "frontend_bytes_in",
    "frontend_msgs_out",
    "frontend_bytes_out",
    "backend_msgs_in",
    "backend_bytes_in",
    "backend_msgs_out",
    "backend_bytes_out",
)
_CMND = b"CMND"
#: a message from a robot or operator may carry a robot name after the topic
_MAX_FRAME = MAX_MESSAGE_BYTES + 1 + MAX_NAME_LEN


def _allowed_keys(roster: Roster) -> dict[str, frozenset[bytes]]:
    """The CURVE keys each side of the relay lets in (z85)."""
    return {
        ROBOTS_DOMAIN: roster.robot_curve_keys(),
        OPERATORS_DOMAIN: frozenset(roster.by_curve_key()),
    }


def _roles(roster: Roster) -> dict[bytes, str]:
    """Each operator's CURVE key (z85) and role: what the command path checks."""
    return {key: op.role for key, op in roster.by_curve_key().items()}


class KeyAllowlist:
    """The CURVE keys one side of the relay accepts (pyzmq authenticator's callback hook)."""

    def __init__(self, keys: frozenset[bytes], what: str) -> None:
        self.keys = keys
        self.what = what
        self.refused = 0
        self._log = BurstLog(log, f"CURVE handshake refused ({what})")

    def callback(self, domain: str, z85_client_key: bytes) -> bool:
        if z85_client_key in self.keys:
            return True
        self.refused += 1
        self._log(f"key {z85_client_key.decode('ascii', 'replace')} is not a roster {self.what}")
        return False


class _TelemetryProxy:
    """``zmq.proxy_steerable`` on its own thread, stopped and queried through its control socket."""

    def __init__(self, ctx: zmq.Context, frontend: zmq.Socket, backend: zmq.Socket) -> None:
        self._control = ctx.socket(zmq.PAIR)
        self._control.setsockopt(zmq.LINGER, 0)
        address = f"inproc://relay-telemetry-control-{id(self)}"
        self._control.bind(address)
        peer = ctx.socket(zmq.PAIR)
        peer.setsockopt(zmq.LINGER, 0)
        peer.connect(address)
        self._lock = threading.Lock()
        self._thread = threading.Thread(
            target=self._run, args=(frontend, backend, peer), name="relay-telemetry", daemon=True
        )
        self._thread.start()

    @staticmethod
    def _run(frontend: zmq.Socket, backend: zmq.Socket, control: zmq.Socket) -> None:
        try:
            zmq.proxy_steerable(frontend, backend, None, control)
        except zmq.ContextTerminated:
            pass
        except zmq.ZMQError as e:
            log.error("telemetry proxy ended: %s", e)
        finally:
            for sock in (frontend, backend, control):
                sock.close(0)

    def statistics(self, timeout_s: float = 1.0) -> dict[str, int]:
        """libzmq's counters: messages and bytes each way (frontend = the robots' side)."""
        with self._lock:
            if not self._thread.is_alive():
                return {}
            self._control.send(b"STATISTICS")
            if not self._control.poll(round(timeout_s * 1000)):
                return {}
            frames = self._control.recv_multipart()
        return {
            name: struct.unpack("=Q", frame)[0]
            for name, frame in zip(PROXY_STAT_NAMES, frames, strict=False)
        }

    def stop(self) -> None:
        with self._lock:
            if self._thread.is_alive():
                self._control.send(b"TERMINATE")
                self._thread.join(5)
            self._control.close(0)


class _CommandPath:
    """Operators' XSUB -> robots' XPUB, dropping commands from keys that may not command."""

    def __init__(
        self,
        ctx: zmq.Context,
        frontend: zmq.Socket,
        backend: zmq.Socket,
        roles: dict[bytes, str] | None,
    ) -> None:
        self.frontend, self.backend = frontend, backend
        self.roles = roles  # z85 CURVE key -> role; None = no CURVE, nothing to check against
        self.counters: Counter[str] = Counter()
        self._stop = threading.Event()
        self._dropped = BurstLog(log, "command dropped at the relay")
        self._thread = threading.Thread(target=self._run, name="relay-commands", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        front, back = self.frontend, self.backend
        poller = zmq.Poller()
        poller.register(front, zmq.POLLIN)
        poller.register(back, zmq.POLLIN)
        try:
            while not self._stop.is_set():
                ready = dict(poller.poll(100))
                if back in ready:  # robots' subscriptions, upstream to the operators' PUBs
                    while back.get(zmq.EVENTS) & zmq.POLLIN:
                        front.send(back.recv(zmq.NOBLOCK))
                if front in ready:
                    for _ in range(256):
                        if not front.get(zmq.EVENTS) & zmq.POLLIN:
                            break
                        self._forward(front.recv(zmq.NOBLOCK, copy=False))
        except zmq.ContextTerminated:
            pass
        finally:
            front.close(0)
            back.close(0)

    def _forward(self, frame: zmq.Frame) -> None:
        if frame.more:  # the protocol is single-frame: drop the rest too
            self.counters["malformed_dropped"] += 1
            while self.frontend.get(zmq.RCVMORE):
                self.frontend.recv(zmq.NOBLOCK, copy=False)
            return
        self.counters["msgs_in"] += 1
        if self.roles is not None and frame.bytes[:TOPIC_LEN] == _CMND:
            key = frame.get("User-Id").encode("ascii", "replace")
            role = self.roles.get(key)
            if role in STOP_ROLES and role != "controller" and _is_arm_stop(frame.bytes):
                self.counters["stops_passed_role"] += 1
            elif role != "controller":
                self.counters["commands_dropped_role"] += 1
                self._dropped(f"key {key.decode()} has role {role}, not controller")
                return
        self.backend.send(frame, zmq.NOBLOCK, copy=False)
        self.counters["msgs_out"] += 1

    @property
    def running(self) -> bool:
        return self._thread.is_alive()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5)


def _is_arm_stop(data: bytes) -> bool:
    """Whether a command frame asks for ``arm_stop`` (read, not verified: the robot verifies)."""
    try:
        _, start = split_name(data)
        body = msgpack.unpackb(data[start:], raw=False)
    except (DecodeError, ValueError, TypeError, msgpack.UnpackException):  # never a stop
        return False
    return isinstance(body, dict) and body.get("action") == "arm_stop"


class Relay:
    """Binds four sockets and forwards until stopped; ``endpoints`` holds what it bound."""

    def __init__(self, config: RelayConfig, ctx: zmq.Context | None = None) -> None:
        self.config = config
        self._own_ctx = ctx is None
        self.ctx = ctx or zmq.Context()
        self.endpoints: dict[str, str] = {}
        self.roster: Roster | None = None
        self._telemetry: _TelemetryProxy | None = None
        self._commands: _CommandPath | None = None
        self._auth: Any = None
        self._allowlists: dict[str, KeyAllowlist] = {}
        self.last_stats: dict[str, float] = {}
        #: set it (SIGHUP: ``systemctl reload``) to read the roster again within a second
        self.roster_reload = threading.Event()
        self.roster_reloads = 0
        self.roster_reloads_failed = 0
        self.reopens = 0
        #: the counters of paths closed by a reopen, so ``stats`` stays cumulative
        self._telemetry_before: Counter[str] = Counter()
        self._commands_before: Counter[str] = Counter()

    def start(self) -> Relay:
        c = self.config
        if c.roster_file is not None:
            self.roster = load_roster(Path(c.roster_file))
        curve = c.security.mode == "curve"
        if curve and self.roster is None:
            raise ConfigError("relay security.mode = 'curve' needs roster_file (who may connect)")
        check = SecurityConfig(mode=c.security.mode, allow_insecure=c.security.allow_insecure)
        for endpoint in self._endpoint_config().values():
            check_endpoint(endpoint, check)
        self._start_auth()
        self._open_paths()
        log.info("relay up: %s", ", ".join(f"{k} {v}" for k, v in self.endpoints.items()))
        return self

    def _open_paths(self, rebind_s: float = 0.0) -> None:
        """Bind the four sockets and start both paths; ``rebind_s``: retry a busy address."""
        tel_in = self._socket(zmq.XSUB, "robots_telemetry_endpoint", ROBOTS_DOMAIN, rebind_s)
        tel_out = self._socket(zmq.XPUB, "operators_telemetry_endpoint", OPERATORS_DOMAIN, rebind_s)
        cmd_in = self._socket(zmq.XSUB, "operators_command_endpoint", OPERATORS_DOMAIN, rebind_s)
        cmd_out = self._socket(zmq.XPUB, "robots_command_endpoint", ROBOTS_DOMAIN, rebind_s)
        cmd_in.send(b"\x01")  # nothing is filtered by topic: roles decide, below
        self._telemetry = _TelemetryProxy(self.ctx, tel_in, tel_out)
        roles = _roles(self.roster) if self.config.security.mode == "curve" else None
        self._commands = _CommandPath(self.ctx, cmd_in, cmd_out, roles)

    def _close_paths(self) -> None:
        """Stop both paths, keeping their counters for ``stats``; the sockets close with them."""
        if self._telemetry is not None:
            self._telemetry_before.update(self._telemetry.statistics())
            self._telemetry.stop()
            self._telemetry = None
        if self._commands is not None:
            self._commands.stop()
            self._commands_before.update(self._commands.counters)
            self._commands = None

    def _reopen_paths(self) -> None:
        """Close every connection and bind again: each client reconnects, through the handshake.

        The only way to cut a key that left the roster: ZeroMQ cannot close one
        peer of a bound socket. Everyone is back within a reconnect interval
        (ZeroMQ's default 100 ms) plus a handshake; a controller's robot may
        meanwhile stop its arm (the deadman), which is the safe side.
        """
        self._close_paths()
        self._open_paths(rebind_s=5.0)

    def _endpoint_config(self) -> dict[str, str]:
        c = self.config
        return {
            "robots_telemetry_endpoint": c.robots_telemetry_endpoint,
            "robots_command_endpoint": c.robots_command_endpoint,
            "operators_telemetry_endpoint": c.operators_telemetry_endpoint,
            "operators_command_endpoint": c.operators_command_endpoint,
        }

    def _socket(self, kind: int, key: str, domain: str, rebind_s: float = 0.0) -> zmq.Socket:
        c = self.config
        sock = self.ctx.socket(kind)
        sock.setsockopt(zmq.LINGER, 0)
        if kind == zmq.XPUB:
            sock.setsockopt(zmq.SNDHWM, c.subscriber_queue)
            sock.setsockopt(zmq.SNDBUF, c.subscriber_sndbuf_bytes)
            sock.setsockopt(zmq.XPUB_NODROP, 0)  # drop for a peer that lags, never block
        else:
            sock.setsockopt(zmq.RCVHWM, c.publisher_queue)
            sock.setsockopt(zmq.MAXMSGSIZE, _MAX_FRAME)
        if c.security.mode == "curve":
            options = server_options(
                SecurityConfig(mode="curve", secret_key_file=c.security.secret_key_file)
            )
            for opt, value in options.items():
                sock.setsockopt(opt, value)
            sock.setsockopt(zmq.ZAP_DOMAIN, domain.encode())
        endpoint = self.endpoints.get(key) or getattr(c, key)  # again: the same port
        deadline = time.monotonic() + rebind_s
        while True:
            try:
                sock.bind(endpoint)
                break
            except zmq.ZMQError as e:
                # the I/O thread closes a socket's listener a moment after close()
                if e.errno == zmq.EADDRINUSE and time.monotonic() < deadline:
                    time.sleep(0.02)
                    continue
                sock.close(0)
                raise ConfigError(f"relay cannot bind {key} {endpoint}: {e}") from None
        self.endpoints[key] = sock.getsockopt(zmq.LAST_ENDPOINT).decode()
        return sock

    def _start_auth(self) -> None:
        if self.config.security.mode != "curve":
            return
        from zmq.auth.thread import ThreadAuthenticator

        what = {ROBOTS_DOMAIN: "robot", OPERATORS_DOMAIN: "operator"}
        self._allowlists = {
            domain: KeyAllowlist(keys, what[domain])
            for domain, keys in _allowed_keys(self.roster).items()
        }
        self._auth = ThreadAuthenticator(self.ctx, log=logging.getLogger("deepxpalm.auth"))
        self._auth.start()
        for domain, allowlist in self._allowlists.items():
            self._auth.configure_curve_callback(domain=domain, credentials_provider=allowlist)

    def reload_roster(self) -> bool:
        """Read ``roster_file`` again; a broken file keeps the roster in force.

        From the next handshake an added key gets in and a removed one is
        refused; from the next message a key no longer a controller has its
        commands dropped. When a key left the roster, every connection is
        closed and bound again (``_reopen_paths``), so its open connection ends
        and its reconnect is refused; the others are back in a moment.
        """
        path = self.config.roster_file
        if path is None:
            log.warning("roster reload asked, but this relay has no roster_file")
            return False
        try:
            roster = load_roster(Path(path))
        except ConfigError as e:
            self.roster_reloads_failed += 1
            log.error("roster reload failed, the roster in force stays: %s", e)
            return False
        old = self.roster
        self.roster = roster
        allowed = _allowed_keys(roster)
        gone: set[bytes] = set()
        if old is not None:
            for domain, keys in _allowed_keys(old).items():
                gone |= keys - allowed[domain]
        for domain, allowlist in self._allowlists.items():
            allowlist.keys = allowed[domain]  # one attribute: the handshake thread reads either
        if self._commands is not None and self._commands.roles is not None:
            self._commands.roles = _roles(roster)
        self.roster_reloads += 1
        log.info(
            "roster %s reloaded: %d operators, %d robots; %d keys removed",
            path,
            len(roster.operators),
            len(roster.robots),
            len(gone),
        )
        if gone and self._allowlists and self._telemetry is not None:
            log.warning("closing every connection so the %d removed keys lose theirs", len(gone))
            self._reopen_paths()
            self.reopens += 1
        return True

    def stats(self) -> dict[str, float]:
        out: dict[str, float] = {"roster_reloads": float(self.roster_reloads)}
        if self.roster_reloads_failed:
            out["roster_reloads_failed"] = float(self.roster_reloads_failed)
        if self.reopens:
            out["reopens"] = float(self.reopens)
        telemetry = Counter(self._telemetry_before)
        if self._telemetry is not None:
            telemetry.update(self._telemetry.statistics())
        for key, value in telemetry.items():
            out[f"telemetry_{key}"] = float(value)
        commands = Counter(self._commands_before)
        if self._commands is not None:
            commands.update(self._commands.counters)
        for key, value in commands.items():
            out[f"commands_{key}" if not key.startswith("commands") else key] = float(value)
        for domain, allowlist in self._allowlists.items():
            out[f"curve_refused_{domain}"] = float(allowlist.refused)
        return out

    def alive(self) -> bool:
        """Both paths forwarding: the proxy answers its control socket, the command loop runs."""
        telemetry, commands = self._telemetry, self._commands
        if telemetry is None or commands is None or not commands.running:
            return False
        return bool(telemetry.statistics(timeout_s=0.5))

    def run(self, stop: threading.Event, duration_s: float | None = None) -> None:
        """Forward until ``stop`` (or ``duration_s``), logging the counters now and then.

        Under systemd (``Type=notify``) it says READY once bound and pings the
        watchdog only while both paths answer, so a wedged proxy is restarted.
        """
        from common.sd_notify import Notifier

        if self._telemetry is None:
            self.start()
        notifier = Notifier()
        notifier.ready(f"relay up: {len(self.endpoints)} endpoints")
        interval = self.config.stats_interval_s
        t_end = None if duration_s is None else time.monotonic() + duration_s
        next_log = time.monotonic() + interval if interval > 0 else None
        try:
            while not stop.is_set():
                now = time.monotonic()
                if t_end is not None and now >= t_end:
                    break
                deadlines = [d for d in (t_end, next_log, now + 1.0) if d is not None]
                stop.wait(max(0.0, min(deadlines) - now))
                if self.roster_reload.is_set():
                    self.roster_reload.clear()
                    self.reload_roster()
                if notifier.enabled and self.alive():
                    notifier.watchdog()
                if next_log is not None and time.monotonic() >= next_log:
                    log.info("relay counters: %s", self.stats())
                    next_log += interval
        finally:
            notifier.stopping()
            notifier.close()
            self.close()

    def close(self) -> None:
        if self._telemetry is not None or self._commands is not None:
            self.last_stats = self.stats()
        self._close_paths()
        if self._auth is not None:
            self._auth.stop()
            self._auth = None
        if self._own_ctx:
            self.ctx.term()

    def __enter__(self) -> Relay:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()
