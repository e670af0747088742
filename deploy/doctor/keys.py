"""CURVE keys: this node's pair, the robot's public key, the operator allowlist."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from common.devices.preflight import (
    FAIL,
    PASS,
    current_user_name,
    groups_of,
    owner_text,
    permits,
    user_named,
)
from deploy.doctor.report import SERVICE_GROUPS, DoctorOptions, Report


def _check_secret_key(report: Report, role: str, path: Path | None, options: DoctorOptions):
    """The node's own key pair. Returns the Z85 public key, or None."""
    import zmq
    import zmq.auth

    name = f"keys: {role} secret"
    key = f"{role}.link.security.secret_key_file"
    if path is None:
        report.add(
            name,
            FAIL,
            f"security.mode = 'curve' but {key} is not set",
            f"`deepxpalm keys generate --dir /etc/deepxpalm/keys --name {role}` and set {key}",
        )
        return None
    try:
        st = path.stat()
    except FileNotFoundError:
        report.add(
            name,
            FAIL,
            f"{path} does not exist",
            f"make the pair on this machine: `deepxpalm keys generate --dir {path.parent} "
            f"--name {path.name.removesuffix('.key_secret')}` (secret keys never travel)",
        )
        return None
    except PermissionError:
        report.add(
            name,
            FAIL,
            f"cannot reach {path}: permission denied on a directory above it",
            f"run doctor as the service user: `sudo -u {options.service_user} deepxpalm "
            "doctor ...`",
        )
        return None
    try:
        public, secret = zmq.auth.load_certificate(path)
    except PermissionError:
        report.add(
            name,
            FAIL,
            f"cannot read {path} ({owner_text(st)}) as {current_user_name()}",
            f"run doctor as the service user (`sudo -u {options.service_user} deepxpalm "
            "doctor ...`) or fix the owner",
        )
        return None
    except (OSError, ValueError) as e:
        report.add(
            name,
            FAIL,
            f"{path} is not a CURVE certificate: {e}",
            "regenerate it with `deepxpalm keys generate`",
        )
        return None
    if secret is None:
        report.add(
            name,
            FAIL,
            f"{path} holds only a public key",
            f"point {key} at the NAME.key_secret file, not NAME.key",
        )
        return None
    if st.st_mode & 0o077:
        report.add(
            name,
            FAIL,
            f"{path} is open to other users ({owner_text(st)}): whoever reads it can "
            "impersonate this node",
            f"chmod 600 {path}",
        )
        return None
    if zmq.curve_public(secret) != public:
        report.add(
            name,
            FAIL,
            f"{path}: its public key is not the one its secret key makes (an edited or "
            "mixed-up file)",
            "regenerate the pair with `deepxpalm keys generate --force` and redistribute "
            "the public half",
        )
        return None
    detail = f"{path} ({owner_text(st)}) is a valid pair, public {public.decode()}"
    service = user_named(options.service_user)
    if service is not None and not permits(
        st, service.pw_uid, groups_of(service, SERVICE_GROUPS), os.R_OK
    ):
        report.add(
            name,
            FAIL,
            f"{detail}, but the service user {options.service_user} cannot read it",
            f"chown {options.service_user}:{options.service_user} {path}",
        )
        return None
    report.add(name, PASS, detail)
    sibling = path.with_name(path.name.removesuffix("_secret"))
    if sibling != path and sibling.exists():
        try:
            sib_public, _ = zmq.auth.load_certificate(sibling)
        except (OSError, ValueError):
            sib_public = None
        if sib_public != public:
            report.add(
                f"keys: {role} public",
                FAIL,
                f"{sibling} is not the public half of {path.name}: copies made from it "
                "for the other machine will be refused",
                f"regenerate the pair together (`deepxpalm keys generate --force`) and copy "
                f"the new {sibling.name}",
            )
    return public


def _load_public(path: Path) -> bytes:
    import zmq.auth

    public, secret = zmq.auth.load_certificate(path)
    if secret is not None:
        raise ValueError("it holds a SECRET key: give the public NAME.key file")
    return public


def check_keys(report: Report, role: str, security: Any, options: DoctorOptions) -> None:
    """The CURVE keys, one by one: a failed handshake never says which key is wrong."""
    if security.mode != "curve":
        return
    own = _check_secret_key(report, role, security.secret_key_file, options)
    if role == "robot":
        directory = security.authorized_keys_dir
        name = "keys: operator allowlist"
        if directory is None or not Path(directory).is_dir():
            report.add(
                name,
                FAIL,
                f"robot.link.security.authorized_keys_dir {directory} is not a directory",
                "copy each operator's NAME.key here and `deepxpalm keys allow operator.key "
                "--authorized /etc/deepxpalm/keys/operators`",
            )
            return
        good, bad = [], []
        for path in sorted(Path(directory).glob("*.key")):
            try:
                public = _load_public(path)
            except (OSError, ValueError) as e:
                bad.append(f"{path.name} ({e})")
                continue
            if own is not None and public == own:
                bad.append(f"{path.name} (this robot's own key, not an operator's)")
                continue
            good.append(path.name)
        if bad:
            report.add(
                name,
                FAIL,
                f"unusable entries in {directory}: {'; '.join(bad)}",
                "remove them; allow each operator's public NAME.key with `deepxpalm keys allow`",
            )
        elif not good:
            report.add(
                name,
                FAIL,
                f"{directory} holds no operator key: nobody can connect",
                "copy the operator's NAME.key here: `deepxpalm keys allow operator.key "
                f"--authorized {directory}`",
            )
        else:
            report.add(name, PASS, f"{len(good)} operator key(s) allowed: {', '.join(good)}")
    else:
        path = security.server_public_key_file
        name = "keys: robot public"
        if path is None:
            report.add(
                name,
                FAIL,
                "operator.link.security.server_public_key_file is not set",
                "copy robot.key from the robot PC and point server_public_key_file at it",
            )
            return
        try:
            if not Path(path).exists():  # pyzmq says "Invalid certificate file" for this too
                raise FileNotFoundError(path)
            public = _load_public(Path(path))
        except FileNotFoundError:
            report.add(
                name,
                FAIL,
                f"{path} does not exist",
                "copy robot.key (the public half) from the robot PC's /etc/deepxpalm/keys",
            )
            return
        except (OSError, ValueError) as e:
            report.add(name, FAIL, f"{path}: {e}", "copy robot.key from the robot PC again")
            return
        if own is not None and public == own:
            report.add(
                name,
                FAIL,
                f"{path} is this operator's own public key, not the robot's",
                "copy robot.key from the robot PC",
            )
            return
        report.add(
            name,
            PASS,
            f"{path} loads, public {public.decode()} (the handshake below proves it is the "
            "robot's)",
        )
