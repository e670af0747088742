"""The router's configuration: every default in one place, printed by --help."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from common.config.typed import param
from router_side.acl import RateLimits


@dataclass
class RouterConfig:
    listen_endpoint: str = param(
        "quic/127.0.0.1:7447",
        "where robots and operators connect: quic/ADDRESS:PORT (UDP); 0.0.0.0 for every "
        "interface; port 0: a free one, said in its READY=1. The address they dial must be "
        "in the router's certificate (--host)",
    )
    roster_file: Path | None = param(
        None,
        "who may connect and what each may put and read (common/keys/roster.py); required. "
        "SIGHUP (systemctl reload) reads it again and restarts the router's session: "
        "nodes reconnect by themselves",
    )
    cert_dir: Path | None = param(
        None,
        "holds the router's NAME.crt and NAME.key and the fabric's ca.crt "
        "(`deepxpalm keys certs --roster ROSTER --dir DIR --router-host HOST`); required",
    )
    name: str = param("router", "the router's certificate name (its common name)")
    max_sessions: int = param(
        64,
        "connections at once at most (robots, operators, and those still in their "
        "handshake): a peer that churns connections cannot take more",
    )
    accept_timeout_ms: float = param(
        2000.0, "a connection that has not finished its handshake by then is closed"
    )
    accept_pending: int = param(16, "handshakes in progress at once at most")
    rates: RateLimits = param(RateLimits(), "per peer and key, messages a second at most")
    status_file: Path | None = param(
        None, "the router writes its state here (roster in force, peers) every few seconds"
    )
