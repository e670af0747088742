"""The relay's configuration: every default in one place, printed by --help."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from common.config import param


@dataclass
class RelaySecurityConfig:
    mode: Literal["plain", "curve"] = param(
        "plain", "curve: every hop encrypted, only the roster's robot and operator keys get in"
    )
    secret_key_file: Path | None = param(
        None, "the relay's key pair (NAME.key_secret from `deepxpalm keys generate`)"
    )
    allow_insecure: bool = param(
        False, "allow plain TCP on a non-loopback address (anyone on the path can read it)"
    )


@dataclass
class RelayConfig:
    robots_telemetry_endpoint: str = param(
        "tcp://127.0.0.1:5575", "XSUB bound here: robots connect their telemetry (XPUB) to it"
    )
    robots_command_endpoint: str = param(
        "tcp://127.0.0.1:5576", "XPUB bound here: robots connect their command SUB to it"
    )
    operators_telemetry_endpoint: str = param(
        "tcp://127.0.0.1:5585", "XPUB bound here: operators connect their telemetry SUB to it"
    )
    operators_command_endpoint: str = param(
        "tcp://127.0.0.1:5586", "XSUB bound here: operators connect their command PUB to it"
    )
    roster_file: Path | None = param(
        None,
        "who may connect, each operator's role and each robot key's names (common/roster.py); "
        "needed with curve. Commands from keys whose role is not controller are dropped here "
        "(and again at the robot), and a robot key may publish and receive under its own names "
        "only. SIGHUP (systemctl reload) reads it again; a file that would remove every robot "
        "or every controller is refused unless it says allow_lockout = true",
    )
    roster_status_file: Path | None = param(
        None,
        "the relay writes the roster in force here (who, since when, and the last reload it "
        "refused), for `deepxpalm doctor --role relay`; unset = not written",
    )
    subscriber_queue: int = param(
        100,
        "messages queued for one subscriber at most (XPUB SNDHWM); beyond it a subscriber "
        "that stops reading is dropped from, never waited for",
    )
    subscriber_sndbuf_bytes: int = param(
        65536,
        "kernel send buffer per subscriber connection: with the queue above, what a stalled "
        "or slow subscriber can hold before the relay drops its messages",
    )
    publisher_queue: int = param(1000, "messages queued from one publisher at most (RCVHWM)")
    stats_interval_s: float = param(10.0, "log the relay's counters this often; 0 = never")
    security: RelaySecurityConfig = param(RelaySecurityConfig(), "CURVE and its key")
