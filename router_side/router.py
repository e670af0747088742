"""The router process: a Zenoh session in router mode, configured from the roster.

Zenoh does the routing, the encryption, the access control and the limits in
its own threads; this process builds the config (zenoh_config.py), opens the
session, tells systemd it is ready, writes a status file, and on SIGHUP reads
the roster again and opens a new session with it (Zenoh cannot change an
access control list in place): connected nodes lose the router for the time
of a restart and reconnect by themselves.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from pathlib import Path
from typing import Any

from common.errors import ConfigError
from common.fabric.session import cert_files, open_session
from common.keys.roster import Roster, check_replacement, load_roster
from common.process.sd_notify import Notifier
from router_side.config import RouterConfig
from router_side.zenoh_config import router_config

log = logging.getLogger(__name__)

STATUS_EVERY_S = 2.0
#: the main thread's turn: how soon a SIGHUP's reload starts
TURN_S = 0.1
#: how long a reload waits for the closed session's port to be free again
REOPEN_S = 5.0


class Router:
    def __init__(self, config: RouterConfig) -> None:
        if config.roster_file is None:
            raise ConfigError(
                "router roster_file is unset: the router admits only the roster's members"
            )
        self.config = config
        self.files = cert_files(config.cert_dir, config.name, "router")
        self.roster: Roster = load_roster(config.roster_file)
        self._roster_sha256 = _sha256(config.roster_file)
        self.roster_reload = threading.Event()
        self.session: Any = None
        self.started_at = time.time()
        self.reloads = 0
        self.reloads_refused = 0
        self.last_refusal = ""

    def zenoh_config(self) -> dict[str, Any]:
        return router_config(self.config, self.roster, self.files)

    def start(self) -> Router:
        if _port_of(self.config.listen_endpoint) == 0:
            self.session = self._open_on_own_port()
        else:
            self.session = open_session(self.zenoh_config(), "router")
        log.info("router up on %s: %s", self.config.listen_endpoint, self.roster.summary())
        return self

    def _open_on_own_port(self) -> Any:
        """``quic/HOST:0``: a UDP port free on HOST, chosen here (Zenoh cannot say which one
        it bound), kept for every later session (a reload); said in READY=1."""
        from common.errors import LinkError

        wildcard = self.config.listen_endpoint
        for attempt in range(OWN_PORT_ATTEMPTS):
            self.config.listen_endpoint = _with_free_port(wildcard)
            try:
                return open_session(self.zenoh_config(), "router")
            except LinkError as e:  # taken between the look and the bind
                if "Address already in use" not in str(e) or attempt + 1 == OWN_PORT_ATTEMPTS:
                    raise
        raise AssertionError("unreachable")

    @property
    def endpoint(self) -> str:
        return self.config.listen_endpoint

    def reload(self) -> bool:
        """Read the roster again; a new session with it, or the old one kept (and why)."""
        try:
            roster = load_roster(self.config.roster_file)
            check_replacement(self.roster, roster, self.config.roster_file)
        except ConfigError as e:
            self.reloads_refused += 1
            self.last_refusal = str(e)
            log.error("roster reload refused, the roster in force stays: %s", e)
            return False
        self.roster = roster
        self._roster_sha256 = _sha256(self.config.roster_file)
        self.session.close()
        self.session = self._reopen()
        self.reloads += 1
        log.info("roster reloaded, router restarted: %s", roster.summary())
        return True

    def _reopen(self) -> Any:
        """A new session with the roster in force; the old one's UDP port may take a moment to
        be released after its close, so the listener is tried again for up to ``REOPEN_S``."""
        from common.errors import LinkError

        deadline = time.monotonic() + REOPEN_S
        while True:
            try:
                return open_session(self.zenoh_config(), "router")
            except LinkError as e:
                if "Address already in use" not in str(e) or time.monotonic() > deadline:
                    raise
                time.sleep(0.05)

    def stats(self) -> dict[str, Any]:
        peers: list[str] = []
        if self.session is not None and not self.session.is_closed():
            try:
                peers = [str(t.zid) for t in self.session.info.transports()]
            except Exception:  # a session closing under us
                peers = []
        return {
            "endpoint": self.config.listen_endpoint,
            "roster": self.roster.summary(),
            "roster_sha256": self._roster_sha256,
            "peers": len(peers),
            "reloads": self.reloads,
            "reloads_refused": self.reloads_refused,
            "last_refusal": self.last_refusal,
            "up_s": round(time.time() - self.started_at, 1),
        }

    def _write_status(self) -> None:
        path = self.config.status_file
        if path is None:
            return
        tmp = Path(path).with_suffix(".tmp")
        tmp.write_text(json.dumps(self.stats(), indent=2, sort_keys=True))
        tmp.replace(path)

    def run(self, stop: threading.Event, duration_s: float | None = None) -> None:
        notifier = Notifier()
        # where it listens (a port-0 config's port too), for whoever started it
        notifier.ready(f"routing for {self.roster.summary()}", {"listen": self.endpoint})
        t_end = None if duration_s is None else time.monotonic() + duration_s
        interval = notifier.watchdog_interval_s
        every = min(STATUS_EVERY_S, interval / 2) if interval else STATUS_EVERY_S
        next_status = 0.0
        try:
            while not stop.is_set():
                now = time.monotonic()
                if t_end is not None and now >= t_end:
                    break
                if self.roster_reload.is_set():
                    self.roster_reload.clear()
                    self.reload()
                if now >= next_status:
                    self._write_status()
                    notifier.watchdog()
                    next_status = now + every
                # a reload (SIGHUP) is taken within a turn; Zenoh routes in its own threads
                stop.wait(TURN_S if t_end is None else max(0.0, min(TURN_S, t_end - now)))
        finally:
            notifier.stopping()
            self.close()

    def close(self) -> None:
        if self.session is not None:
            self.session.close()
            self.session = None


#: how often a router told to listen on port 0 tries another free port
OWN_PORT_ATTEMPTS = 5


def _port_of(endpoint: str) -> int | None:
    """The port of ``quic/HOST:PORT`` (None when it names none)."""
    port = endpoint.split("?", 1)[0].rpartition(":")[2]
    return int(port) if port.isdigit() else None


def _with_free_port(endpoint: str) -> str:
    """``quic/HOST:0`` with a UDP port free on HOST right now."""
    import socket

    address, _, _ = endpoint.split("?", 1)[0].removeprefix("quic/").rpartition(":")
    host = address.strip("[]")
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_DGRAM) as probe:
        probe.bind((host, 0))
        port = probe.getsockname()[1]
    return f"quic/{address}:{port}"


def _sha256(path: Path) -> str:
    """The roster file's digest: the doctor tells the roster in force from the one on disk."""
    import hashlib

    return hashlib.sha256(Path(path).read_bytes()).hexdigest()
