"""The relay: ZeroMQ's XSUB -> XPUB forwarding between sites that both connect out to it.

Robot nodes and operator nodes connect *out* to the relay, so neither site
opens an inbound port. Two paths, each an XSUB (publishers connect) and an
XPUB (subscribers connect) joined by a small loop that also carries the
subscriptions back upstream:

- **telemetry** (robots -> operators). Routing is ZeroMQ's prefix
  subscription on the topic and robot name (docs/protocol.md, Robot names),
  so a robot sees what anyone asks for and skips raw frames nobody wants. A
  subscriber that stops reading fills only its own queue (``SNDHWM`` plus
  the kernel buffer) and is then dropped from: an XPUB never blocks on one
  peer (``XPUB_NODROP`` off). With CURVE each message arrives with its
  sender's key (ZAP ``User-Id``), and one whose robot name is not among
  that key's roster names is dropped and counted (``telemetry_dropped_name``):
  one robot's PC cannot pose as another robot.
- **commands** (operators -> robots). A ``CMND`` from a key whose roster
  role is not ``controller`` is dropped and counted, except an ``arm_stop``
  from a role that may stop (``STOP_ROLES``: an observer may press STOP;
  the robot checks the signer's role again). The robots' XPUB takes
  subscriptions by hand (``XPUB_MANUAL``): a robot key's subscription is
  applied only for its own names, so it cannot read another robot's
  commands (``commands_subscriptions_refused_name``).

Each subscriber connection's subscriptions are kept apart (``_Subscriptions``).
The ZAP handler tags every handshake with a connection number, which libzmq
attaches to every message of that connection, so the relay knows which
connection sent each (un)subscription and what it holds. An unsubscribe for a
prefix that connection does not hold is ignored, counted
(``*_unsubscribes_ignored``) and logged; it never reaches another peer's
subscriptions nor the publishers. Upstream, the telemetry path forwards the
union: a prefix goes to the robots when its first holder asks and leaves when
its last holder drops it or closes. The command path forwards nothing
upstream (the relay's own catch-all already asks the operators for
everything); a robot connection's unsubscribe only ever narrows its own
connection. Anything else a subscriber sends (a frame that is not a
subscription) is dropped, counted (``*_subscriber_frames_dropped``) and logged
with its key; every socket has a message size limit, the subscribers' sides a
small one, so a large frame closes only its sender's connection, before it is
stored.

The relay reads only the topic and name of a message (and a command's
action); it never verifies a signature. Both paths run at tens to hundreds
of messages a second, which a Python loop carries in microseconds each
(docs/benchmarks.md, Relay).

The relay holds no key that can command a robot: commands are signed by the
operator (common/signing.py) and the robot checks them against its own
roster, so a compromised relay can delay or drop, never command
(docs/security.md).
"""

from __future__ import annotations

import hashlib
import itertools
import json
import logging
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
from common.messages import ROLES, STOP_ROLES
from common.roster import Roster, RosterLockoutError, check_replacement, parse_roster
from common.security import SecurityConfig, check_endpoint, server_options
from relay_side.config import RelayConfig
from relay_side.connection_log import ConnectionLog

log = logging.getLogger(__name__)

#: ZAP domains: a robot key cannot pose as an operator, nor the reverse
ROBOTS_DOMAIN, OPERATORS_DOMAIN = "robots", "operators"
_CMND = b"CMND"
#: a message from a robot or operator may carry a robot name after the topic
_MAX_FRAME = MAX_MESSAGE_BYTES + 1 + MAX_NAME_LEN
#: what a subscriber may send: a subscription (1 byte + a prefix: topic, name and more). A
#: larger frame closes the sender's connection in libzmq before it is stored; a smaller one
#: that is not a subscription is read, counted, logged with its key and dropped.
_MAX_SUBSCRIBER_FRAME = 64 * 1024
#: a longer subscription prefix is not applied nor forwarded: no message of the protocol
#: needs one, and a robot's socket refuses (and then never reconnects) a subscription over
#: its own message size limit
_MAX_PREFIX = 256
#: the connection number the relay's ZAP handler gives each handshake (a ZAP metadata property)
CONN_PROPERTY = "X-Conn"


def _read_roster(path: Path) -> tuple[Roster, str]:
    """The roster in ``path`` and the SHA-256 of its text (what the doctor compares)."""
    try:
        text = path.read_text()
    except OSError as e:
        raise ConfigError(f"cannot read roster {path}: {e}") from None
    return parse_roster(text, path), hashlib.sha256(text.encode()).hexdigest()


def roster_status(roster: Roster, digest: str, path: Path | None, since: str) -> dict[str, Any]:
    """The relay's roster in force, as it writes it for the doctor."""
    by_role = {role: [op.name for op in roster.operators if op.role == role] for role in ROLES}
    return {
        "roster_file": str(path),
        "sha256": digest,
        "since": since,
        "summary": roster.summary(),
        "robots": {r.name: sorted({r.name, *r.names}) for r in roster.robots},
        **{f"{role}s": names for role, names in by_role.items()},
    }


def _now_text() -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S %z")


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


def _zmtp_property(name: bytes, value: bytes) -> bytes:
    """One property as ZMTP (and a ZAP reply's metadata frame) encodes it."""
    return bytes([len(name)]) + name + len(value).to_bytes(4, "big") + value


def _tagging_authenticator(ctx: zmq.Context) -> Any:
    """pyzmq's ThreadAuthenticator whose every accepted handshake carries a connection number.

    libzmq attaches a ZAP reply's metadata to every message of that
    connection; the relay reads it back (``CONN_PROPERTY``) to keep each
    connection's subscriptions apart. Without CURVE the same handler admits
    every NULL handshake (pyzmq's rule with no address list) and still tags it.
    """
    from zmq.auth.thread import ThreadAuthenticator

    class TaggingAuthenticator(ThreadAuthenticator):
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            self.connections = itertools.count(1)

        def _send_zap_reply(
            self,
            request_id: bytes,
            status_code: bytes,
            status_text: bytes,
            user_id: str | bytes = "anonymous",
        ) -> None:
            if status_code != b"200":
                super()._send_zap_reply(request_id, status_code, status_text, user_id)
                return
            if isinstance(user_id, str):
                user_id = user_id.encode("utf-8", "replace")
            conn = str(next(self.connections)).encode()
            metadata = _zmtp_property(CONN_PROPERTY.encode(), conn)
            self.zap_socket.send_multipart(
                [b"1.0", request_id, status_code, status_text, user_id, metadata]
            )

    return TaggingAuthenticator(ctx, log=logging.getLogger("deepxpalm.auth"))


class _Peer:
    """Who sent a frame from a subscriber: its connection (None: a closed connection's
    unsubscribe, which libzmq sends with no metadata), its socket fd and its CURVE key."""

    __slots__ = ("conn", "fd", "key")

    def __init__(self, frame: zmq.Frame) -> None:
        self.conn: int | None = None
        self.fd = -1
        self.key = b""
        try:
            frame.get("Socket-Type")  # every live connection's messages carry it
        except (zmq.ZMQError, AttributeError):
            return
        self.key = _sender(frame)
        try:
            self.fd = int(frame.get("__fd"))  # libzmq's own property (ZMQ_SRCFD)
        except (zmq.ZMQError, ValueError, AttributeError):
            self.fd = -1
        try:
            self.conn = int(frame.get(CONN_PROPERTY))
        except (zmq.ZMQError, ValueError, AttributeError):
            # no tag (cannot happen with the relay's ZAP handler): the fd, made unique
            self.conn = -2 - self.fd

    def text(self) -> str:
        if self.conn is None:
            return "a closed connection"
        key = self.key.decode("ascii", "replace") or "(no key)"
        return f"key {key} (connection {self.conn})"


class _Subscriptions:
    """Each subscriber connection's prefixes, and how many connections hold each prefix.

    A connection is the relay's ZAP number for it (``_Peer.conn``). libzmq says
    when a connection closes only through that connection's unsubscribes, with
    no metadata; on the telemetry path (``closes_count``) those are counted
    against each prefix (``closed``), which keeps ``count`` exact without
    knowing which connection closed. A closed connection's record is dropped
    when a newer connection arrives on its socket fd (one live connection per
    fd), or when none holds the prefix any more. Records are capped; past the
    cap a prefix is still counted but not recorded, so its holder's unsubscribe
    is ignored and the prefix stays subscribed upstream: more traffic, never
    less.
    """

    def __init__(self, closes_count: bool, max_per_conn: int = 256, max_total: int = 65536):
        self.closes_count = closes_count
        self.max_per_conn, self.max_total = max_per_conn, max_total
        self.held: dict[int, set[bytes]] = {}
        self.holders: dict[bytes, set[int]] = {}
        self.count: Counter[bytes] = Counter()
        self.fd_conn: dict[int, int] = {}
        self.records = 0

    def seen(self, peer: _Peer) -> None:
        """A live connection's frame: a connection older on the same fd has closed."""
        if peer.fd < 0 or peer.conn is None:
            return
        old = self.fd_conn.get(peer.fd)
        if old == peer.conn:
            return
        if old is not None and old < peer.conn:
            self._forget(old)
        if old is None or old < peer.conn:
            self.fd_conn[peer.fd] = peer.conn

    def _forget(self, conn: int) -> None:
        for prefix in self.held.pop(conn, ()):
            self.records -= 1
            holders = self.holders.get(prefix)
            if holders is not None:
                holders.discard(conn)
                if not holders:
                    del self.holders[prefix]
            if not self.closes_count:  # nothing else will take it off the count
                self._decrement(prefix)

    def holds(self, conn: int, prefix: bytes) -> bool:
        return prefix in self.held.get(conn, ())

    def full(self, conn: int) -> bool:
        return len(self.held.get(conn, ())) >= self.max_per_conn or self.records >= self.max_total

    def add(self, conn: int, prefix: bytes) -> bool:
        """``conn`` holds ``prefix`` (again: no change); True when it is the first holder."""
        if self.holds(conn, prefix):
            return False
        if not self.full(conn):
            self.held.setdefault(conn, set()).add(prefix)
            self.holders.setdefault(prefix, set()).add(conn)
            self.records += 1
        self.count[prefix] += 1
        return self.count[prefix] == 1

    def remove(self, conn: int, prefix: bytes) -> bool:
        """``conn`` (which holds it) drops ``prefix``; True when nobody holds it any more."""
        held = self.held[conn]
        held.discard(prefix)
        if not held:
            del self.held[conn]
        self.records -= 1
        holders = self.holders[prefix]
        holders.discard(conn)
        if not holders:
            del self.holders[prefix]
        return self._decrement(prefix)

    def closed(self, prefix: bytes) -> bool:
        """A closed connection held ``prefix``; True when nobody holds it any more."""
        return self._decrement(prefix)

    def _decrement(self, prefix: bytes) -> bool:
        n = self.count.get(prefix, 0)
        if n <= 0:
            return False
        if n > 1:
            self.count[prefix] = n - 1
            return False
        del self.count[prefix]
        for conn in self.holders.pop(prefix, ()):  # every remaining record is a closed one's
            held = self.held.get(conn)
            if held is not None:
                held.discard(prefix)
                self.records -= 1
                if not held:
                    del self.held[conn]
        return True


#: a path's loop is stuck when it has not turned for this long (its poll waits 100 ms)
_STUCK_S = 2.0


class _Path:
    """Publishers' XSUB -> subscribers' XPUB on its own thread, subscriptions carried back.

    ``names``: each robot CURVE key (z85) and the wire names it may use; None
    (no CURVE) checks nothing. Replaced whole on a roster reload (one
    attribute, read once per message).
    """

    what = "path"
    #: a closed connection's unsubscribes are exactly what it held (libzmq, XPUB not manual)
    closes_count = True

    def __init__(
        self,
        frontend: zmq.Socket,
        backend: zmq.Socket,
        names: dict[bytes, frozenset[bytes]] | None,
    ) -> None:
        self.frontend, self.backend = frontend, backend
        self.names = names
        self.counters: Counter[str] = Counter()
        self.subscriptions = _Subscriptions(closes_count=self.closes_count)
        self._ignored = BurstLog(log, f"unsubscribe ignored at the relay ({self.what})")
        self._junk = BurstLog(log, f"frame from a subscriber dropped at the relay ({self.what})")
        self.turned = time.monotonic()
        self.connections = ConnectionLog(backend, self.what, self.counters)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"relay-{self.what}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        front, back = self.frontend, self.backend
        poller = zmq.Poller()
        poller.register(front, zmq.POLLIN)
        poller.register(back, zmq.POLLIN)
        poller.register(self.connections.monitor, zmq.POLLIN)
        try:
            while not self._stop.is_set():
                ready = dict(poller.poll(100))
                self.turned = time.monotonic()
                if self.connections.monitor in ready:
                    self.connections.handle()
                if back in ready:  # from the subscribers: subscriptions only
                    while back.get(zmq.EVENTS) & zmq.POLLIN:
                        self._from_subscriber(back.recv(zmq.NOBLOCK, copy=False))
                if front in ready:
                    for _ in range(256):
                        if not front.get(zmq.EVENTS) & zmq.POLLIN:
                            break
                        self._forward(front.recv(zmq.NOBLOCK, copy=False))
        except zmq.ContextTerminated:
            pass
        except zmq.ZMQError as e:
            log.error("relay %s path ended: %s", self.what, e)
        finally:
            self.connections.close()
            front.close(0)
            back.close(0)

    def _from_subscriber(self, frame: zmq.Frame) -> None:
        """A frame from the subscribers' side: a subscription, or something to drop."""
        data = frame.bytes
        peer = _Peer(frame)
        if peer.conn is not None:
            self.connections.heard(peer.fd, peer.text())
        if frame.more or not data or data[0] not in (0, 1):
            parts = 1
            while self.backend.get(zmq.RCVMORE):
                self.backend.recv(zmq.NOBLOCK, copy=False)
                parts += 1
            self.counters["subscriber_frames_dropped"] += 1
            self._junk(
                f"{peer.text()} sent {len(data)} bytes ({parts} frames) starting "
                f"{data[:8]!r}: a subscriber sends subscriptions only"
            )
            return
        self.subscriptions.seen(peer)
        prefix = data[1:]
        if data[0] == 1:
            if len(prefix) > _MAX_PREFIX:
                self.counters["subscriptions_refused_length"] += 1
                self._junk(f"{peer.text()} asked for a {len(prefix)}-byte prefix (at most "
                           f"{_MAX_PREFIX}): not forwarded to the publishers")  # fmt: skip
            elif peer.conn is not None:  # libzmq sends no subscription for a closed connection
                self._subscribe(peer, prefix)
        elif peer.conn is None:
            self._closed(prefix)
        elif self.subscriptions.holds(peer.conn, prefix):
            self._unsubscribe(peer, prefix)
        else:
            self.counters["unsubscribes_ignored"] += 1
            self._ignored(
                f"{peer.text()} dropped {_prefix_text(prefix)}, which that connection does not hold"
            )

    def _subscribe(self, peer: _Peer, prefix: bytes) -> None:
        if self.subscriptions.add(peer.conn, prefix):
            self.frontend.send(b"\x01" + prefix)

    def _unsubscribe(self, peer: _Peer, prefix: bytes) -> None:
        if self.subscriptions.remove(peer.conn, prefix):
            self.frontend.send(b"\x00" + prefix)

    def _closed(self, prefix: bytes) -> None:
        if self.subscriptions.closed(prefix):
            self.frontend.send(b"\x00" + prefix)

    def _forward(self, frame: zmq.Frame) -> None:
        if frame.more:  # the protocol is single-frame: drop the rest too
            self.counters["malformed_dropped"] += 1
            while self.frontend.get(zmq.RCVMORE):
                self.frontend.recv(zmq.NOBLOCK, copy=False)
            return
        self.counters["msgs_in"] += 1
        if not self._admit(frame):
            return
        self.backend.send(frame, zmq.NOBLOCK, copy=False)
        self.counters["msgs_out"] += 1

    def _admit(self, frame: zmq.Frame) -> bool:
        return True

    @property
    def running(self) -> bool:
        return self._thread.is_alive() and time.monotonic() - self.turned < _STUCK_S

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5)


def _claimed_name(data: memoryview | bytes) -> bytes:
    """The robot name a frame (or a subscription prefix) carries after its topic; b"" if none."""
    n = data[TOPIC_LEN] if len(data) > TOPIC_LEN else 0
    if not 1 <= n <= MAX_NAME_LEN or len(data) < TOPIC_LEN + 1 + n:
        return b""
    return bytes(data[TOPIC_LEN + 1 : TOPIC_LEN + 1 + n])


def _sender(frame: zmq.Frame) -> bytes:
    """The CURVE key (z85) the frame's connection authenticated with; b"" if none."""
    try:
        return frame.get("User-Id").encode("ascii", "replace")
    except (zmq.ZMQError, AttributeError):  # no metadata: a subscription of a closed pipe
        return b""


def _prefix_text(prefix: bytes) -> str:
    if not prefix:
        return "everything (the empty prefix)"
    name = _claimed_name(prefix)
    return f"{prefix[:TOPIC_LEN]!r} of robot {name.decode()}" if name else repr(prefix[:40])


def _names_text(names: frozenset[bytes] | None) -> str:
    return ", ".join(sorted(n.decode() for n in names)) if names else "none (not a roster robot)"


class _TelemetryPath(_Path):
    """Robots' XSUB -> operators' XPUB, dropping what a robot key sends under another's name."""

    what = "telemetry"

    def __init__(self, *args: Any) -> None:
        self._posing = BurstLog(log, "telemetry dropped at the relay: a robot key posing")
        super().__init__(*args)

    def _admit(self, frame: zmq.Frame) -> bool:
        names = self.names
        if names is None:
            return True
        key = _sender(frame)
        mine = names.get(key)
        data = frame.buffer
        claimed = _claimed_name(data)
        if mine is not None and claimed in mine:
            return True
        self.counters["dropped_name"] += 1
        self._posing(
            f"key {key.decode()} sent {bytes(data[:TOPIC_LEN])!r} as robot "
            f"{claimed.decode() or '(no name)'}; it may use {_names_text(mine)}"
        )
        return False


class _CommandPath(_Path):
    """Operators' XSUB -> robots' XPUB: commands only from controllers (a STOP from any who may
    press one), and each robot key subscribed to its own names' commands only."""

    what = "commands"
    #: XPUB_MANUAL: a closed connection's unsubscribes name what it asked for, granted or not
    closes_count = False

    def __init__(
        self,
        frontend: zmq.Socket,
        backend: zmq.Socket,
        names: dict[bytes, frozenset[bytes]] | None,
        roles: dict[bytes, str] | None,
    ) -> None:
        self.roles = roles  # z85 CURVE key -> role; None = no CURVE, nothing to check against
        self._dropped = BurstLog(log, "command dropped at the relay")
        self._refused = BurstLog(log, "subscription refused at the relay: a robot key posing")
        super().__init__(frontend, backend, names)

    def _subscribe(self, peer: _Peer, prefix: bytes) -> None:
        """Applied (XPUB_MANUAL: to this connection only) when the key may read it.

        Nothing goes upstream: the relay's own catch-all subscription already
        asks the operators for every command, so no robot's subscription can
        change what the relay receives.
        """
        names = self.names
        if names is not None:
            mine = names.get(peer.key)
            if mine is None or _claimed_name(prefix) not in mine:
                self.counters["subscriptions_refused_name"] += 1
                self._refused(
                    f"key {peer.key.decode()} asked for {prefix[:TOPIC_LEN]!r} of robot "
                    f"{_claimed_name(prefix).decode() or '(every robot)'}; it may use "
                    f"{_names_text(mine)}"
                )
                return
        if self.subscriptions.holds(peer.conn, prefix):
            return
        if self.subscriptions.full(peer.conn):
            self.counters["subscriptions_refused_count"] += 1
            self._refused(f"{peer.text()} holds {self.subscriptions.max_per_conn} prefixes already")
            return
        self.subscriptions.add(peer.conn, prefix)
        self.backend.setsockopt(zmq.SUBSCRIBE, prefix)

    def _unsubscribe(self, peer: _Peer, prefix: bytes) -> None:
        self.subscriptions.remove(peer.conn, prefix)
        self.backend.setsockopt(zmq.UNSUBSCRIBE, prefix)  # this connection's, and only it

    def _closed(self, prefix: bytes) -> None:
        """libzmq has already taken the closed connection's subscriptions off its own pipe."""

    def _admit(self, frame: zmq.Frame) -> bool:
        if self.roles is not None and frame.bytes[:TOPIC_LEN] == _CMND:
            key = _sender(frame)
            role = self.roles.get(key)
            if role in STOP_ROLES and role != "controller" and _is_arm_stop(frame.bytes):
                self.counters["stops_passed_role"] += 1
            elif role != "controller":
                self.counters["commands_dropped_role"] += 1
                self._dropped(f"key {key.decode()} has role {role}, not controller")
                return False
        return True


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
        self._telemetry: _TelemetryPath | None = None
        self._commands: _CommandPath | None = None
        self._auth: Any = None
        self._allowlists: dict[str, KeyAllowlist] = {}
        self.last_stats: dict[str, float] = {}
        #: set it (SIGHUP: ``systemctl reload``) to read the roster again within a second
        self.roster_reload = threading.Event()
        self.roster_reloads = 0
        self.roster_reloads_failed = 0
        self.roster_reloads_refused = 0
        self._roster_digest = ""
        self._roster_since = ""
        self.reopens = 0
        #: the counters of paths closed by a reopen, so ``stats`` stays cumulative
        self._telemetry_before: Counter[str] = Counter()
        self._commands_before: Counter[str] = Counter()

    def start(self) -> Relay:
        c = self.config
        if c.roster_file is not None:
            self.roster, self._roster_digest = _read_roster(Path(c.roster_file))
            log.info("roster %s in force: %s", c.roster_file, self.roster.summary())
            if not self.roster.robots or not self.roster.controllers():
                log.warning("roster %s lets no robot or no controller in", c.roster_file)
            self._write_roster_status()
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
        curve = self.config.security.mode == "curve"
        # a robot connection's subscription is applied by the relay, to that connection only,
        # and with CURVE only for the key's own names (_CommandPath)
        cmd_out = self._socket(
            zmq.XPUB, "robots_command_endpoint", ROBOTS_DOMAIN, rebind_s, manual=True
        )
        cmd_in.send(b"\x01")  # nothing is filtered by topic: roles decide, below
        names = self.roster.robot_names_by_curve_key() if curve else None
        self._telemetry = _TelemetryPath(tel_in, tel_out, names)
        self._commands = _CommandPath(
            cmd_in, cmd_out, names, _roles(self.roster) if curve else None
        )

    def _close_paths(self) -> None:
        """Stop both paths, keeping their counters for ``stats``; the sockets close with them."""
        if self._telemetry is not None:
            self._telemetry.stop()
            self._telemetry_before.update(self._telemetry.counters)
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

    def _socket(
        self, kind: int, key: str, domain: str, rebind_s: float = 0.0, manual: bool = False
    ) -> zmq.Socket:
        c = self.config
        sock = self.ctx.socket(kind)
        sock.setsockopt(zmq.LINGER, 0)
        if manual:  # before bind: no peer's subscription may be applied by libzmq itself
            sock.setsockopt(zmq.XPUB_MANUAL, 1)
        if kind == zmq.XPUB:
            sock.setsockopt(zmq.SNDHWM, c.subscriber_queue)
            sock.setsockopt(zmq.SNDBUF, c.subscriber_sndbuf_bytes)
            sock.setsockopt(zmq.XPUB_NODROP, 0)  # drop for a peer that lags, never block
            sock.setsockopt(zmq.MAXMSGSIZE, _MAX_SUBSCRIBER_FRAME)
            if not manual:  # every (un)subscription of every connection, to keep them apart
                sock.setsockopt(zmq.XPUB_VERBOSER, 1)
        else:
            sock.setsockopt(zmq.RCVHWM, c.publisher_queue)
            sock.setsockopt(zmq.MAXMSGSIZE, _MAX_FRAME)
        if c.security.mode == "curve":
            options = server_options(
                SecurityConfig(mode="curve", secret_key_file=c.security.secret_key_file)
            )
            for opt, value in options.items():
                sock.setsockopt(opt, value)
        # with or without CURVE: the ZAP handler numbers each connection (_Peer.conn)
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
        self._auth = _tagging_authenticator(self.ctx)
        self._auth.start()
        if self.config.security.mode != "curve":
            return
        what = {ROBOTS_DOMAIN: "robot", OPERATORS_DOMAIN: "operator"}
        self._allowlists = {
            domain: KeyAllowlist(keys, what[domain])
            for domain, keys in _allowed_keys(self.roster).items()
        }
        for domain, allowlist in self._allowlists.items():
            self._auth.configure_curve_callback(domain=domain, credentials_provider=allowlist)

    def reload_roster(self) -> bool:
        """Read ``roster_file`` again; a broken file, or one that would lock the fleet out,
        keeps the roster in force.

        From the next handshake an added key gets in and a removed one is
        refused; from the next message a key no longer a controller has its
        commands dropped and a robot key's telemetry is checked against its new
        names. When a key left the roster or a robot key lost a name, every
        connection is closed and bound again (``_reopen_paths``), so its open
        connection (and its subscriptions) end; the others are back in a moment.
        A roster that would leave no robot or no controller where there were
        some (an empty or truncated file) is refused unless it says
        ``allow_lockout = true`` (common/roster.py).
        """
        path = self.config.roster_file
        if path is None:
            log.warning("roster reload asked, but this relay has no roster_file")
            return False
        old = self.roster
        try:
            roster, digest = _read_roster(Path(path))
            if old is not None:
                check_replacement(old, roster, path)
        except ConfigError as e:
            self.roster_reloads_failed += 1
            if isinstance(e, RosterLockoutError):
                self.roster_reloads_refused += 1
            log.error("roster reload failed, the roster in force stays: %s", e)
            self._write_roster_status(refused=str(e))
            return False
        self.roster, self._roster_digest = roster, digest
        allowed = _allowed_keys(roster)
        gone: set[bytes] = set()
        if old is not None:
            for domain, keys in _allowed_keys(old).items():
                gone |= keys - allowed[domain]
            new_names = roster.robot_names_by_curve_key()
            for key, names in old.robot_names_by_curve_key().items():
                if names - new_names.get(key, frozenset()):
                    gone.add(key)  # it keeps its key but lost a name (and its subscriptions)
        for domain, allowlist in self._allowlists.items():
            allowlist.keys = allowed[domain]  # one attribute: the handshake thread reads either
        if self._allowlists:
            names = roster.robot_names_by_curve_key()
            for path_ in (self._telemetry, self._commands):
                if path_ is not None:
                    path_.names = names
            if self._commands is not None:
                self._commands.roles = _roles(roster)
        self.roster_reloads += 1
        log.info(
            "roster %s reloaded: %s; %d keys removed or narrowed",
            path,
            roster.summary(),
            len(gone),
        )
        self._write_roster_status()
        if gone and self._allowlists and self._telemetry is not None:
            log.warning("closing every connection so the %d removed keys lose theirs", len(gone))
            self._reopen_paths()
            self.reopens += 1
        return True

    def _write_roster_status(self, refused: str | None = None) -> None:
        """What roster is in force, for ``deepxpalm doctor`` (``roster_status_file``)."""
        target, roster = self.config.roster_status_file, self.roster
        if target is None or roster is None:
            return
        if refused is None:
            self._roster_since = _now_text()
        status = roster_status(
            roster, self._roster_digest, self.config.roster_file, self._roster_since
        )
        if refused is not None:
            status["refused"] = {"at": _now_text(), "reason": refused}
        try:
            tmp = Path(target).with_suffix(".tmp")
            tmp.write_text(json.dumps(status, indent=2))
            tmp.replace(target)
        except OSError as e:
            log.warning("cannot write roster_status_file %s: %s", target, e)

    def stats(self) -> dict[str, float]:
        out: dict[str, float] = {"roster_reloads": float(self.roster_reloads)}
        if self.roster_reloads_failed:
            out["roster_reloads_failed"] = float(self.roster_reloads_failed)
        if self.roster_reloads_refused:
            out["roster_reloads_refused"] = float(self.roster_reloads_refused)
        if self.reopens:
            out["reopens"] = float(self.reopens)
        telemetry = Counter(self._telemetry_before)
        if self._telemetry is not None:
            telemetry.update(self._telemetry.counters)
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
        """Both paths' loops running and turning (each wakes at least every 100 ms)."""
        telemetry, commands = self._telemetry, self._commands
        return bool(telemetry and commands and telemetry.running and commands.running)

    def run(self, stop: threading.Event, duration_s: float | None = None) -> None:
        """Forward until ``stop`` (or ``duration_s``), logging the counters now and then.

        Under systemd (``Type=notify``) it says READY once bound and pings the
        watchdog only while both paths' loops turn, so a wedged one is restarted.
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
