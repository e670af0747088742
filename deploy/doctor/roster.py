"""The roster and the robot's signed stream in ``deepxpalm doctor``: what both sides rely on.

A robot judges every command by its own roster; the router admits and routes
by its copy. An operator checks the robot's stream with the robot's public
signing key, so a compromised router cannot make a palm feel what did not
happen.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from common.devices.preflight import FAIL, PASS, WARN
from common.errors import ConfigError, DeepXPalmError
from deploy.doctor.report import Report


def check_roster(report: Report, path: Any, *, need_signing: bool) -> Any | None:
    """The roster loads; a warning when it names no controller (nobody could command)."""
    from common.keys.roster import load_roster

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
        report.add(
            "roster", FAIL, str(e), "correct that entry (common/keys/roster.py shows the format)"
        )
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
    elif not need_signing and not roster.robots:  # the router host: robots get in by it
        report.add("roster", WARN, detail + "; no robot: the router admits none", "add them")
    else:
        report.add("roster", PASS, detail)
    return roster


def check_stream_signing(report: Report, role: str, link: Any) -> None:
    """Across sites: is the robot's stream signed, and does the operator check it?"""
    path = link.signing_key_file if role == "robot" else link.robot_key_file
    setting = "link.signing_key_file" if role == "robot" else "link.robot_key_file"
    if path is None:
        opted_out = getattr(link, "unsigned_stream", False)
        report.add(
            "signed stream",
            WARN if opted_out else FAIL,
            f"{setting} is not set"
            + (" (link.unsigned_stream)" if opted_out else ", so the node will not start")
            + ": a compromised router could forge what a palm feels",
            "`deepxpalm keys robot --name NAME` on the robot PC; its NAME.sign_secret is the "
            "robot's link.signing_key_file, its NAME.sign the operators' link.robot_key_file "
            "(docs/deploy.md: A signed stream)",
        )
        return
    from common.wire.signing import load_public_key, load_signer

    try:
        key = load_signer(path).public if role == "robot" else load_public_key(path)
    except DeepXPalmError as e:
        report.add("signed stream", FAIL, str(e), "generate it again or correct the path")
        return
    report.add("signed stream", PASS, f"the robot's key {key.hex()}")
