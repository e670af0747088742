"""A node's Zenoh session to the fabric's router: its config, and how it is opened.

A node connects out to a router (``router_endpoint``) as a Zenoh client, on
QUIC with mutual TLS: the router admits only a certificate its CA signed, and
knows the node by the certificate's common name, the node's roster name. QUIC
in "mixed reliability" carries reliable messages (commands, heartbeats) on a
stream and best-effort ones (stimuli, frames, STOP's extra copies) as
datagrams, so a lost packet delays only the message it carried.

If the router goes away the session keeps trying to reach it (every
``retry_ms``, doubling up to 1 s); what is put meanwhile is dropped, never
queued, and the node sees the silence through its own freshness rules.
"""

from __future__ import annotations

import json
import logging
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from common.config.typed import param
from common.errors import ConfigError, LinkError
from common.fabric.certificates import CertFiles, common_name
from common.wire.codec import MAX_MESSAGE_BYTES

log = logging.getLogger(__name__)

#: a peer silent this long is gone (Zenoh's link lease; keep-alives every quarter of it): a
#: router killed without a goodbye is noticed in this time, and nodes reconnect to the one
#: systemd started again. Longer than the outages a lossy path has (2 s), shorter than
#: Zenoh's 10 s default, which kept nodes away from a restarted router for 8 s
LEASE_MS = 3000
#: batches each priority's transmit queue holds (Zenoh's default: 2 for every priority). An
#: express message takes a batch of its own, and a message under congestion control DROP waits
#: 1 ms for a free one before it is dropped, reliable or not: with two, a burst of express
#: messages (a viewer's offers, a jog beside a gripper command, a page's answers) lost some
#: whenever a busy machine kept the transmit thread off a core for a millisecond. Commands and
#: video signals (their priorities in ``link._qos``) get Zenoh's largest queue, and so do the
#: heartbeats: latest-value, but they feed the robot's deadman and the lease, and with two a
#: recorder beside two busy loops missed 9 of a robot's 161. A best-effort message waits in
#: this queue only while the transmit thread is off the core (QUIC takes a datagram at once),
#: and the receiver keeps the newest. The stimuli keep two (a stop shares their priority and
#: has its copies and resends instead), the frames too. Batches are allocated as used
TX_QUEUE_BATCHES = {"interactive_high": 16, "interactive_low": 16, "data": 16}
#: how long a node's first connect keeps trying its router before the open fails. One try
#: (Zenoh's default for a client) failed now and then beside busy loops, the router answering
#: every other node: a handshake lost once is tried again in ``retry_ms``. A router that is
#: not there is reported after this long, and the node exits for systemd to start again
FIRST_CONNECT_MS = 3000
#: how long closing a session may take before the node goes on without waiting for it
CLOSE_WAIT_S = 1.0
#: Zenoh's own framing around a message: the key, the QoS and the sequence number
FRAMING_BYTES = 1024
#: what a router or node accepts as one (defragmented) message at most: the codec's limit
MAX_WIRE_MESSAGE_BYTES = MAX_MESSAGE_BYTES + FRAMING_BYTES


@dataclass
class FabricConfig:
    router_endpoint: str = param(
        "quic/127.0.0.1:7447",
        "the router to connect out to (deepxpalm router): quic/HOST:PORT; HOST must be a "
        "name or address in the router's certificate",
    )
    cert_dir: Path | None = param(
        None,
        "holds this node's NAME.crt and NAME.key and the fabric's ca.crt (`deepxpalm keys "
        "certs`); NAME is the roster name: the robot's link.robot_name, the operator's own",
    )
    name: str = param(
        "",
        "our roster name, the certificate's common name; empty = the robot's "
        "link.robot_name, or for an operator the one certificate in cert_dir",
    )
    retry_ms: float = param(
        250.0, "how soon a lost router is tried again (doubling up to 1 s while it is away)"
    )


def cert_files(cert_dir: Path | None, name: str, where: str) -> CertFiles:
    """The certificate files of ``name`` in ``cert_dir``, checked to exist and to be its own."""
    if cert_dir is None:
        raise ConfigError(
            f"{where}.cert_dir is unset: the fabric needs this node's certificate "
            "(`deepxpalm keys certs --roster ROSTER --dir DIR`)"
        )
    files = CertFiles.in_dir(cert_dir, name)
    files.check(f"{where}.cert_dir")
    cn = common_name(files.cert)
    if cn != name:
        raise ConfigError(f"{files.cert} is {cn!r}'s certificate, not {name!r}'s")
    return files


def only_member(cert_dir: Path, where: str) -> str:
    """The one member certificate in ``cert_dir`` (an operator PC holds its own only)."""
    names = sorted(p.stem for p in Path(cert_dir).glob("*.crt") if p.stem != "ca")
    if len(names) != 1:
        raise ConfigError(
            f"{where}.name is unset and {cert_dir} holds {len(names)} member certificates "
            f"({', '.join(names) or 'none'}): set {where}.name to ours"
        )
    return names[0]


def member_name(fabric: FabricConfig, default: str | None, where: str) -> str:
    """Our roster name: ``fabric.name``, else ``default`` (a robot's name on the wire), else
    the one member certificate in ``fabric.cert_dir``."""
    if fabric.name:
        return fabric.name
    if default:
        return default
    if fabric.cert_dir is None:
        raise ConfigError(
            f"{where}.cert_dir is unset: the fabric needs our certificate "
            "(`deepxpalm keys certs --roster ROSTER --dir DIR`)"
        )
    return only_member(fabric.cert_dir, where)


def open_member_session(fabric: FabricConfig, member: str, where: str, what: str) -> Any:
    """``member``'s session to its router, with its certificate from ``fabric.cert_dir``."""
    files = cert_files(fabric.cert_dir, member, where)
    return open_session(client_config(fabric, files, where), what)


def _endpoint(endpoint: str, where: str) -> str:
    if not endpoint.startswith("quic/"):
        raise ConfigError(
            f"{where}.router_endpoint {endpoint!r} must be quic/HOST:PORT: only QUIC carries "
            "best-effort messages as datagrams beside reliable ones, encrypted"
        )
    base = endpoint.split("?", 1)[0]
    return base + "?mixed_rel=1"


def tls_section(files: CertFiles, *, listen: bool = False) -> dict[str, Any]:
    """Zenoh's ``transport.link.tls``: our certificate for both ends, the CA, mutual TLS."""
    tls: dict[str, Any] = {
        "root_ca_certificate": str(files.ca),
        "connect_private_key": str(files.key),
        "connect_certificate": str(files.cert),
        "enable_mtls": True,
        "verify_name_on_connect": True,
    }
    if listen:
        tls["listen_private_key"] = str(files.key)
        tls["listen_certificate"] = str(files.cert)
    return tls


def quiet_discovery() -> dict[str, Any]:
    """No multicast or gossip: a node talks to the router it was given, nothing else."""
    return {"multicast": {"enabled": False}, "gossip": {"enabled": False}}


def client_config(fabric: FabricConfig, files: CertFiles, where: str) -> dict[str, Any]:
    """The Zenoh config of a node's session (a client of one router)."""
    retry = max(10.0, fabric.retry_ms)
    return {
        "mode": "client",
        "connect": {
            "endpoints": [_endpoint(fabric.router_endpoint, where)],
            # the first connect keeps trying for a while; a lost router is tried again forever
            "timeout_ms": FIRST_CONNECT_MS,
            "exit_on_failure": False,
            "retry": {
                "period_init_ms": round(retry),
                "period_max_ms": round(max(retry, 1000.0)),
                "period_increase_factor": 2,
            },
        },
        "listen": {"endpoints": []},
        "scouting": quiet_discovery(),
        "transport": {
            "link": {
                "tls": tls_section(files),
                "rx": {"max_message_size": MAX_WIRE_MESSAGE_BYTES},
                "tx": tx_section(),
            },
        },
    }


def tx_section() -> dict[str, Any]:
    """How a node's or the router's links send: the lease, keep-alives, the queues."""
    return {"lease": LEASE_MS, "keep_alive": 4, "queue": {"size": dict(TX_QUEUE_BATCHES)}}


def open_session(config: dict[str, Any], what: str) -> Any:
    """A Zenoh session from a config dict; LinkError with the reason if Zenoh refuses it."""
    try:
        import zenoh
    except ImportError:
        raise ConfigError(
            "the fabric needs eclipse-zenoh: pip install 'deepxpalm[fabric]'"
        ) from None
    try:
        return zenoh.open(zenoh.Config.from_json5(json.dumps(config)))
    except zenoh.ZError as e:
        endpoints = config.get("connect", {}).get("endpoints") or []
        if config.get("mode") == "client" and "Unable to connect" in str(e):
            raise LinkError(
                f"{what}: no router answered at {', '.join(endpoints)} with our certificate: is "
                "`deepxpalm router` running there, UDP open to it, its certificate naming the "
                "host we dial, and its CA ours? (a node that lost its router later reconnects "
                "by itself; one that never reached it exits, and systemd starts it again)"
            ) from None
        raise LinkError(f"{what}: Zenoh refused to open its session: {e}") from None


def close_session(session: Any, wait_s: float = CLOSE_WAIT_S) -> bool:
    """Close ``session``, waiting at most ``wait_s``; True if it closed in that time.

    Zenoh's close waits for its links to say goodbye; with the router gone it
    waits for a peer that will not answer. A node stopping (the arm already
    stopped by then) must not hang on that: the close goes on in a thread of
    its own and the process ends without it.
    """
    done = threading.Event()

    def close() -> None:
        try:
            session.close()
        except Exception as e:  # already closed, or closing under us
            log.debug("closing the Zenoh session: %s", e)
        finally:
            done.set()

    threading.Thread(target=close, name="zenoh-close", daemon=True).start()
    if done.wait(wait_s):
        return True
    log.warning("the Zenoh session did not close within %.1f s (router unreachable?)", wait_s)
    return False
