"""The fabric across sites: this node's certificate, the router, and the other side through it.

What a node with ``link.mode = "fabric"`` needs before a session: its own
certificate (the roster name as its common name, signed by the fabric's CA,
not about to expire, its key readable by this user only), a router that
answers on QUIC and admits that certificate, and (for an operator) its robot
heard through the router. Each check opens what the node itself would open.
"""

from __future__ import annotations

import datetime
import stat
import time
from typing import Any

from common.devices.preflight import FAIL, PASS, SKIP, WARN
from common.errors import ConfigError
from deploy.doctor.report import DoctorOptions, Report

#: a certificate that expires sooner than this is a warning
RENEW_WITHIN_DAYS = 30


def _member(role: str, config: Any) -> str | None:
    from common.fabric.session import member_name

    default = config.link.robot_name if role == "robot" else None
    try:
        return member_name(config.link.fabric, default, f"{role}.link.fabric")
    except ConfigError:
        return None


def check_certificate(report: Report, role: str, config: Any) -> Any:
    """This node's certificate files, their name, signer, expiry and the key's mode."""
    from common.fabric.session import cert_files

    name = "fabric: certificate"
    member = _member(role, config)
    fix = (
        "on the machine that keeps the fabric's CA: `deepxpalm keys certs --roster ROSTER "
        "--dir DIR`, then copy this member's NAME.crt, NAME.key and ca.crt to "
        f"{role}.link.fabric.cert_dir"
    )
    if member is None:
        report.add(name, FAIL, f"no roster name: set {role}.link.fabric.name", fix)
        return None
    try:
        files = cert_files(config.link.fabric.cert_dir, member, f"{role}.link.fabric")
    except ConfigError as e:
        report.add(name, FAIL, str(e), fix)
        return None
    return check_certificate_files(report, files, member, fix)


def check_certificate_files(report: Report, files: Any, member: str, fix: str) -> Any:
    """A member's certificate: signed by the fabric's CA, its key private, not about to expire;
    ``files`` if it passes or only warns, else None."""
    from cryptography import x509

    name = "fabric: certificate"
    try:
        cert = x509.load_pem_x509_certificate(files.cert.read_bytes())
        ca = x509.load_pem_x509_certificate(files.ca.read_bytes())
        cert.verify_directly_issued_by(ca)
    except (OSError, ValueError, TypeError) as e:
        report.add(name, FAIL, f"{files.cert} is not signed by {files.ca}: {e}", fix)
        return None
    if stat.S_IMODE(files.key.stat().st_mode) & 0o077:
        report.add(
            name,
            FAIL,
            f"{files.key} is readable by other users",
            f"chmod 600 {files.key} (owned by the service user)",
        )
        return None
    left = cert.not_valid_after_utc - datetime.datetime.now(datetime.UTC)
    if left.days < RENEW_WITHIN_DAYS:
        status = FAIL if left.total_seconds() <= 0 else WARN
        report.add(name, status, f"{member}'s certificate expires in {left.days} days", fix)
        return files
    report.add(name, PASS, f"{member}'s, signed by the fabric's CA, {left.days} days left")
    return files


def check_router(report: Report, role: str, config: Any, files: Any, options: DoctorOptions):
    """The router answers and admits our certificate; for an operator, its robot is heard."""
    from common.fabric import keyexprs
    from common.fabric.session import client_config, close_session, open_session

    name = "fabric: router"
    if files is None:
        report.add(name, SKIP, "not checked: no certificate")
        return
    fabric = config.link.fabric
    zconfig = client_config(fabric, files, f"{role}.link.fabric")
    # a node tries its router once and exits; the doctor gives it the peer timeout to answer
    # (QUIC's own handshake timeout, seconds, would make an absent router a long wait)
    zconfig["connect"]["timeout_ms"] = round(max(options.peer_timeout_s, 1.0) * 1000)
    try:
        session = open_session(zconfig, "doctor")
    except Exception as e:  # ConfigError, LinkError, or one of Zenoh's own
        report.add(
            name,
            FAIL,
            str(e),
            "is `deepxpalm router` running there, UDP open to it, its certificate naming the "
            "host we dial (`--router-host`), and our CA its CA?",
        )
        return
    try:
        deadline = time.monotonic() + max(options.peer_timeout_s, 1.0)
        while time.monotonic() < deadline and not list(session.info.routers_zid()):
            time.sleep(0.05)
        if not list(session.info.routers_zid()):
            report.add(
                name,
                FAIL,
                f"no router answered at {fabric.router_endpoint} with our certificate",
                "is `deepxpalm router` running there, UDP open to it, its certificate naming "
                "the host we dial (`--router-host`), and our CA its CA?",
            )
            return
        report.add(name, PASS, f"{fabric.router_endpoint} admitted our certificate")
        if role != "operator" or not options.check_peer:
            return
        robot = config.link.robot_name
        heard: list[bytes] = []
        sub = session.declare_subscriber(
            keyexprs.robot_key(robot, "heartbeat"), lambda s: heard.append(b"")
        )
        deadline = time.monotonic() + options.peer_timeout_s
        while time.monotonic() < deadline and not heard:
            time.sleep(0.05)
        sub.undeclare()
        if heard:
            report.add("fabric: robot", PASS, f"{robot}'s heartbeats arrive through the router")
        else:
            report.add(
                "fabric: robot",
                WARN,
                f"no heartbeat of {robot} in {options.peer_timeout_s:g} s",
                f"is the robot node up with link.robot_name = {robot!r}, and does the roster "
                "let this operator read it?",
            )
    finally:
        close_session(session)


def check_fabric(report: Report, role: str, config: Any, options: DoctorOptions) -> None:
    from deploy.doctor.roster import check_roster, check_stream_signing

    if role == "robot":
        check_roster(report, config.link.roster_file, need_signing=True)
    check_stream_signing(report, role, config.link)
    files = check_certificate(report, role, config)
    check_router(report, role, config, files, options)
