"""The whole Zenoh config of the router: listener, certificates, ACL and limits."""

from __future__ import annotations

from typing import Any

from common.errors import ConfigError
from common.fabric.certificates import CertFiles
from common.fabric.session import (
    MAX_WIRE_MESSAGE_BYTES,
    quiet_discovery,
    tls_section,
    tx_section,
)
from common.keys.roster import Roster
from router_side.acl import access_control, rate_gates, size_filter
from router_side.config import RouterConfig


def listen_endpoint(endpoint: str) -> str:
    """The listener, with QUIC's mixed reliability offered to every client that asks."""
    if not endpoint.startswith("quic/"):
        raise ConfigError(
            f"router listen_endpoint {endpoint!r} must be quic/ADDRESS:PORT: the fabric runs "
            "on QUIC (encrypted, with datagrams for best-effort messages)"
        )
    return endpoint.split("?", 1)[0] + "?mixed_rel=auto"


def router_config(config: RouterConfig, roster: Roster, files: CertFiles) -> dict[str, Any]:
    return {
        "mode": "router",
        "listen": {"endpoints": [listen_endpoint(config.listen_endpoint)]},
        "connect": {"endpoints": []},
        "scouting": quiet_discovery(),
        # queries, storages, the admin space: none of them is the fabric's
        "adminspace": {"enabled": False},
        "access_control": access_control(roster),
        "low_pass_filter": size_filter(),
        "downsampling": rate_gates(config.rates, roster),
        "transport": {
            "unicast": {
                "accept_timeout": round(config.accept_timeout_ms),
                "accept_pending": config.accept_pending,
                "max_sessions": config.max_sessions,
                "max_links": 1,
            },
            "link": {
                "tls": tls_section(files, listen=True),
                "rx": {"max_message_size": MAX_WIRE_MESSAGE_BYTES},
                "tx": tx_section(),
            },
        },
    }
