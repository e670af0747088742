"""The router host in ``deepxpalm doctor --role router``.

The config parses as the router reads it, the roster loads and names robots
and a controller, the router's certificate is there (signed by the fabric's
CA, not about to expire, its key private), and its UDP port is free, or held
by a running router whose status file then says which roster it holds.
"""

from __future__ import annotations

import hashlib
import json
import socket
from pathlib import Path
from typing import Any

from common.config.typed import from_dict
from common.devices.preflight import FAIL, PASS, SKIP, WARN
from common.errors import ConfigError
from deploy.doctor.fabric import check_certificate_files
from deploy.doctor.report import DoctorOptions, Report
from deploy.doctor.roster import check_roster


def _udp_port(endpoint: str) -> tuple[str, int] | None:
    """(host, port) of ``quic/HOST:PORT``; None for anything else."""
    _, _, address = endpoint.partition("/")
    host, sep, port = address.split("?")[0].rpartition(":")
    if not sep or not port.isdigit():
        return None
    return host.strip("[]"), int(port)


def _port_free(host: str, port: int) -> str | None:
    """None if we could bind the UDP port now, otherwise why not."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_DGRAM) as s:
        try:
            s.bind((host, port))
        except OSError as e:
            return e.strerror or str(e)
    return None


def _roster_in_force(report: Report, config: Any) -> None:
    """What the running router holds (its ``status_file``), against the file on disk."""
    if config.status_file is None:
        report.add(
            "roster in force",
            SKIP,
            "status_file is not set: the router does not say what it holds",
            'set status_file = "/var/lib/deepxpalm/router-status.json"',
        )
        return
    try:
        status = json.loads(Path(config.status_file).read_text())
    except (OSError, ValueError) as e:
        report.add("roster in force", SKIP, f"no status from a router yet ({e})")
        return
    held = f"{status.get('roster')}, {status.get('peers')} peer(s)"
    on_disk = hashlib.sha256(Path(config.roster_file).read_bytes()).hexdigest()
    if status.get("roster_sha256") in (None, on_disk):
        refusal = status.get("last_refusal")
        if refusal:
            report.add(
                "roster in force",
                WARN,
                f"the router refused a roster ({refusal}); it holds {held}",
                "correct the file and `sudo systemctl reload deepxpalm-router`",
            )
        else:
            report.add("roster in force", PASS, f"the router holds {held}")
    else:
        report.add(
            "roster in force",
            WARN,
            f"the file on disk changed since the router read it; it holds {held}",
            "`sudo systemctl reload deepxpalm-router` to take it in",
        )


def diagnose_router(report: Report, data: dict[str, Any], options: DoctorOptions) -> None:
    """Every check for the router host."""
    from common.fabric.session import cert_files
    from router_side.config import RouterConfig

    try:
        config = from_dict(RouterConfig, data, where="router")
    except ConfigError as e:
        report.add("config", FAIL, str(e), "`deepxpalm router --help` lists every setting")
        return
    report.add("config", PASS, f"router config valid ({report.source})")
    roster = check_roster(report, config.roster_file, need_signing=False)
    fix = (
        "`deepxpalm keys certs --roster ROSTER --dir DIR --router-host HOST` on the machine "
        "that keeps the fabric's CA, then router.cert_dir = DIR"
    )
    try:
        files = cert_files(config.cert_dir, config.name, "router")
    except ConfigError as e:
        report.add("fabric: certificate", FAIL, str(e), fix)
    else:
        check_certificate_files(report, files, config.name, fix)
    where = _udp_port(config.listen_endpoint)
    if where is None:
        report.add("port", FAIL, f"{config.listen_endpoint} is not quic/ADDRESS:PORT", "correct it")
        return
    why = _port_free(*where)
    if why is None:
        report.add("port", PASS, f"{config.listen_endpoint}: UDP port free to bind")
        return
    report.add(
        "port",
        WARN,
        f"{config.listen_endpoint} is in use ({why}): the router running?",
        "stop it for a full check (`sudo systemctl stop deepxpalm-router`), or free the port",
    )
    if roster is not None:
        _roster_in_force(report, config)
