"""The relay in ``deepxpalm doctor``: on the relay host, and from a robot or operator in relay mode.

On the relay host (``--role relay``): the config parses as the relay reads
it, the roster loads and names at least one robot and one controller, the
relay's secret key is there and private, and the four ports are free (or
held by a running relay, which is then probed instead). From a robot or an
operator whose link goes through a relay: the roster (robot) loads and
holds signing keys, the robot's name is one the protocol allows, and the
relay's two endpoints this node connects to accept TCP connections.
"""

from __future__ import annotations

import os
import socket
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from common.config import from_dict
from common.errors import ConfigError, DeepXPalmError
from common.preflight import FAIL, PASS, SKIP, WARN, tcp_probe
from deploy.doctor.report import DoctorOptions, Report

_RELAY_ENDPOINTS = (
    "robots_telemetry_endpoint",
    "robots_command_endpoint",
    "operators_telemetry_endpoint",
    "operators_command_endpoint",
)


def _host_port(endpoint: str) -> tuple[str, int] | None:
    if not endpoint.startswith("tcp://"):
        return None
    parts = urlsplit(endpoint)
    try:
        return parts.hostname or "*", parts.port
    except ValueError:
        return None


def check_roster(report: Report, path: Any, *, need_signing: bool) -> Any | None:
    """The roster loads; a warning when it names no controller (nobody could command)."""
    from common.roster import load_roster

    if path is None:
        report.add(
            "roster",
            FAIL,
            "no roster_file set",
            "write one (docs/deploy.md, The roster) and set it",
        )
        return None
    try:
        roster = load_roster(Path(path))
    except ConfigError as e:
        report.add("roster", FAIL, str(e), "correct that entry (common/roster.py shows the format)")
        return None
    roles = [op.role for op in roster.operators]
    detail = f"{path}: {roster.summary()}"
    if need_signing and not roster.by_signing_key():
        report.add(
            "roster",
            FAIL,
            detail + "; no operator has a signing_key, so no command can ever be obeyed",
            "add each operator's NAME.sign (from `deepxpalm keys generate-signing`)",
        )
    elif "controller" not in roles:
        report.add(
            "roster", WARN, detail + "; no controller: nobody can command", "give one the role"
        )
    elif not need_signing and not roster.robots:  # the relay host: robots get in by it
        report.add("roster", WARN, detail + "; no robot: the relay lets none in", "add them")
    else:
        report.add("roster", PASS, detail)
    return roster


def _roster_in_force(report: Report, config: Any) -> None:
    """What the running relay holds (its ``roster_status_file``), against the file on disk."""
    import hashlib
    import json

    status_path = config.roster_status_file
    if status_path is None:
        report.add(
            "roster in force",
            SKIP,
            "roster_status_file is not set: the relay does not say what it holds",
            'set roster_status_file = "/var/lib/deepxpalm/relay-roster.json"',
        )
        return
    try:
        status = json.loads(Path(status_path).read_text())
    except (OSError, ValueError) as e:
        report.add("roster in force", SKIP, f"no status from a relay yet ({e})")
        return
    held = f"since {status.get('since')}: {status.get('summary')}"
    refused = status.get("refused")
    try:
        on_disk = hashlib.sha256(Path(config.roster_file).read_bytes()).hexdigest()
    except OSError:
        on_disk = None
    if on_disk == status.get("sha256"):
        report.add("roster in force", PASS, f"the file on disk, {held}")
    elif refused:
        report.add(
            "roster in force",
            WARN,
            f"the relay refused the file on disk at {refused.get('at')} "
            f"({refused.get('reason')}); it keeps the roster it had {held}",
            "correct the file and reload (`sudo systemctl reload deepxpalm-relay`)",
        )
    else:
        report.add(
            "roster in force",
            WARN,
            f"the file on disk changed since the relay read it; it holds the roster {held}",
            "`sudo systemctl reload deepxpalm-relay` to take it in",
        )


def _secret_key(report: Report, path: Any) -> None:
    if path is None:
        report.add("keys: relay", FAIL, "security.secret_key_file is not set",
                   "`deepxpalm keys generate --dir /etc/deepxpalm/keys --name relay`")  # fmt: skip
        return
    p = Path(path)
    if not p.is_file():
        report.add("keys: relay", FAIL, f"{p} does not exist", "generate it or correct the path")
        return
    mode = p.stat().st_mode & 0o777
    if mode & 0o077:
        report.add(
            "keys: relay",
            FAIL,
            f"{p} is mode {mode:o}: others can read the secret",
            f"chmod 600 {p}",
        )
        return
    report.add("keys: relay", PASS, f"{p} (mode {mode:o})")


def _port_free(host: str, port: int) -> str | None:
    """None if we could bind it now, otherwise why not."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("" if host == "*" else host, port))
        except OSError as e:
            return os.strerror(e.errno) if e.errno else str(e)
    return None


def diagnose_relay(report: Report, data: dict[str, Any], options: DoctorOptions) -> None:
    """Every check for the relay host."""
    from relay_side.config import RelayConfig

    try:
        config = from_dict(RelayConfig, data, where="relay")
    except ConfigError as e:
        report.add("config", FAIL, str(e), "`deepxpalm relay --help` lists every setting")
        return
    report.add("config", PASS, f"relay config valid ({report.source})")
    curve = config.security.mode == "curve"
    if curve or config.roster_file is not None:
        check_roster(report, config.roster_file, need_signing=False)
        _roster_in_force(report, config)
    if curve:
        _secret_key(report, config.security.secret_key_file)
    else:
        report.add(
            "security",
            WARN,
            "plain: the relay lets anyone in and cannot tell an observer's command from a "
            "controller's (the robots still check signatures)",
            'set security.mode = "curve" with a roster',
        )
    from common.security import SecurityConfig, check_endpoint

    plain = SecurityConfig(mode=config.security.mode, allow_insecure=config.security.allow_insecure)
    held = []
    for key in _RELAY_ENDPOINTS:
        endpoint = getattr(config, key)
        try:
            check_endpoint(endpoint, plain)
        except DeepXPalmError as e:
            report.add(f"endpoint {key}", FAIL, str(e), "use curve off this machine")
            continue
        hp = _host_port(endpoint)
        if hp is None or hp[1] is None:
            continue
        why = _port_free(*hp)
        if why is None:
            report.add(f"port {key}", PASS, f"{endpoint} is free to bind")
        else:
            held.append(endpoint)
            probe = tcp_probe("127.0.0.1" if hp[0] in ("*", "0.0.0.0") else hp[0], hp[1], 1.0)
            status = WARN if probe is None else FAIL
            report.add(
                f"port {key}",
                status,
                f"{endpoint} is in use ({why})"
                + (
                    "; something accepts connections there: the relay running?" if not probe else ""
                ),
                "stop the relay for a full check (`sudo systemctl stop deepxpalm-relay`), or "
                "free the port",
            )


def check_relay_from_node(report: Report, role: str, config: Any, options: DoctorOptions) -> None:
    """A robot or operator that connects out to a relay: names, roster, and the relay's ports."""
    link = config.link
    name = link.robot_name
    from common.codec import DecodeError, check_robot_name

    if not name:
        report.add(
            "robot name",
            FAIL if role == "robot" else WARN,
            "link.robot_name is empty: a relay carries several robots, each under its name",
            "set link.robot_name (the same on the robot and on its operators)",
        )
    else:
        try:
            check_robot_name(name)
            report.add("robot name", PASS, f"{name!r}")
        except DecodeError as e:
            report.add("robot name", FAIL, str(e), "pick a name of A-Z a-z 0-9 _ - .")
    if role == "robot":
        check_roster(report, link.roster_file, need_signing=True)
    elif link.signing_key_file is None:
        report.add(
            "signing key",
            WARN,
            "link.signing_key_file is not set: a robot with a roster ignores our commands",
            "`deepxpalm keys generate-signing` and put NAME.sign's hex in the robot's roster",
        )
    else:
        try:
            from common.signing import load_signer

            signer = load_signer(link.signing_key_file)
            report.add("signing key", PASS, f"public key {signer.public.hex()} (the roster's)")
        except DeepXPalmError as e:
            report.add("signing key", FAIL, str(e), "generate it again or correct the path")
    _check_stream_signing(report, role, link)
    if not options.check_peer:
        report.add("relay", SKIP, "not checked (--no-peer)")
        return
    for endpoint in (link.telemetry_endpoint, link.command_endpoint):
        hp = _host_port(endpoint)
        if hp is None or hp[1] is None:
            continue
        why = tcp_probe(hp[0], hp[1], options.tcp_timeout_s)
        if why is None:
            report.add(f"relay {endpoint}", PASS, "accepts connections")
        else:
            report.add(
                f"relay {endpoint}",
                FAIL,
                why,
                "start the relay (`deepxpalm relay`, deploy/systemd/deepxpalm-relay.service) "
                "and open that port on the relay host only",
            )


def _check_stream_signing(report: Report, role: str, link: Any) -> None:
    """Through a relay: is the robot's stream signed, and does the operator check it?"""
    path = link.signing_key_file if role == "robot" else link.robot_key_file
    setting = "link.signing_key_file" if role == "robot" else "link.robot_key_file"
    if path is None:
        opted_out = getattr(link, "unsigned_stream", False)
        report.add(
            "signed stream",
            WARN if opted_out else FAIL,
            f"{setting} is not set"
            + (" (link.unsigned_stream)" if opted_out else ", so the node will not start")
            + ": a compromised relay could forge what a palm feels",
            "`deepxpalm keys robot --name NAME` on the robot PC; its NAME.sign_secret is the "
            "robot's link.signing_key_file, its NAME.sign the operators' link.robot_key_file "
            "(docs/deploy.md: A signed stream)",
        )
        return
    from common.signing import load_public_key, load_signer

    try:
        key = load_signer(path).public if role == "robot" else load_public_key(path)
    except DeepXPalmError as e:
        report.add("signed stream", FAIL, str(e), "generate it again or correct the path")
        return
    report.add("signed stream", PASS, f"the robot's key {key.hex()}")
