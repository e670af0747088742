"""``deepxpalm doctor``: is this machine ready for a session? A pass/warn/fail list.

    deepxpalm doctor --role robot --config /etc/deepxpalm/robot.toml
    deepxpalm doctor --role operator --config /etc/deepxpalm/operator.toml
    deepxpalm doctor --scene demo --role robot --json

A session fails in the first minute for the same handful of reasons: a
serial device that is not where the config says (or not openable by the
service's user), a key that is missing, readable by everyone or not the one
the other side holds, a peer that cannot be reached through the firewall,
a link too slow for the staleness limits. Each check here runs what the
node itself would run (the same config parser, the real drivers through
``build_device``, the same CURVE options and allowlist, heartbeats through
``ClockSync``), so a pass means the node will get past that point, and each
failure says what to do about it. Exit code 0 only if nothing failed;
warnings (a powersave governor, no real-time scheduling, a peer not started
yet) do not stop a session.

Run it with the node stopped: it opens the devices and binds the robot's
ports itself. When it finds the robot node already running it says so and
skips what the node owns instead of fighting it for the hardware.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import errno
import glob
import importlib
import json
import logging
import os
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from common.clock import now_ns
from common.clock_sync import ClockSync
from common.config import from_dict, load_toml
from common.devices import Device, build_device
from common.errors import ConfigError, DeepXPalmError
from common.overrides import apply_overrides
from common.preflight import (
    PreflightContext,
    current_user_name,
    groups_of,
    owner_text,
    permits,
    processes_holding,
    tcp_probe,
    user_named,
)

log = logging.getLogger(__name__)

PASS, WARN, FAIL, SKIP = "pass", "warn", "fail", "skip"
ROLES = ("robot", "operator")
#: The user the systemd units run as (deploy/systemd/*.service).
SERVICE_USER = "deepxpalm"
#: What the units add to the service user's groups (SupplementaryGroups=).
SERVICE_GROUPS = ("dialout",)
#: (family in the node config, registry module), per role.
FAMILIES = {
    "robot": (
        ("tactile", "robot_side.tactile"),
        ("gripper", "robot_side.gripper"),
        ("arm", "robot_side.arm"),
    ),
    "operator": (("servos", "operator_side.servos"),),
}
HEARTBEAT_PERIOD_S = 0.05
#: Round trips enough for a clock estimate; the exchange stops early once it has them.
CLOCK_SAMPLES = 12


# ----------------------------------------------------------------- results
@dataclass
class Check:
    """One line of the report: what was checked, what was found, and the fix."""

    name: str
    status: str  # pass | warn | fail | skip
    detail: str
    fix: str = ""


@dataclass
class DoctorOptions:
    device_timeout_s: float = 5.0  # connect + status of one device
    peer_timeout_s: float = 3.0  # how long to wait for the other node's heartbeats
    tcp_timeout_s: float = 1.0  # one TCP connect
    connect_devices: bool = True  # False: presence checks only, drivers not opened
    check_peer: bool = True
    service_user: str = SERVICE_USER


@dataclass
class Report:
    role: str
    source: str
    checks: list[Check] = field(default_factory=list)

    def add(self, name: str, status: str, detail: str, fix: str = "") -> Check:
        check = Check(name, status, detail, fix)
        self.checks.append(check)
        log.debug("%s %s: %s", status, name, detail)
        return check

    @property
    def ok(self) -> bool:
        return not any(c.status == FAIL for c in self.checks)

    def counts(self) -> dict[str, int]:
        return {s: sum(c.status == s for c in self.checks) for s in (PASS, WARN, FAIL, SKIP)}

    def failures(self) -> list[Check]:
        return [c for c in self.checks if c.status == FAIL]

    def find(self, name: str) -> Check:
        """The first check whose name starts with ``name`` (for tests and scripts)."""
        for c in self.checks:
            if c.name.startswith(name):
                return c
        raise KeyError(f"no check named {name!r}; have {[c.name for c in self.checks]}")

    def to_dict(self) -> dict[str, Any]:
        return {
            "role": self.role,
            "config": self.source,
            "ok": self.ok,
            "counts": self.counts(),
            "checks": [dataclasses.asdict(c) for c in self.checks],
        }

    def to_text(self) -> str:
        lines = [f"deepxpalm doctor: {self.role} node, config {self.source}", ""]
        width = max((len(c.name) for c in self.checks), default=10)
        for c in self.checks:
            lines.append(f"  {c.status.upper():<4}  {c.name:<{width}}  {c.detail}")
            if c.fix and c.status in (FAIL, WARN):
                lines.append(f"        {'':<{width}}  fix: {c.fix}")
        n = self.counts()
        verdict = "ready for a session" if self.ok else "NOT ready: fix the failures above"
        lines += [
            "",
            f"{n[FAIL]} failed, {n[WARN]} warnings, {n[PASS]} passed, {n[SKIP]} skipped: {verdict}",
        ]
        return "\n".join(lines)


# ------------------------------------------------------------------ config
def node_section(data: dict[str, Any], role: str) -> dict[str, Any]:
    """The node's own table, the way ``load_node_config`` picks it."""
    if isinstance(data.get(role), dict):
        return data[role]
    if any(k in data for k in ("robot", "operator", "network", "scene")):
        return {}
    return data


def infer_role(data: dict[str, Any]) -> str | None:
    present = [r for r in ROLES if isinstance(data.get(r), dict)]
    return present[0] if len(present) == 1 else None


def _config_class(role: str) -> type:
    if role == "robot":
        from robot_side.config import RobotConfig

        return RobotConfig
    from operator_side.config import OperatorConfig

    return OperatorConfig


def _check_config(report: Report, role: str, data: dict[str, Any]) -> Any | None:
    try:
        config = from_dict(_config_class(role), data, where=role)
    except ConfigError as e:
        report.add(
            "config",
            FAIL,
            str(e),
            f"correct that key; `deepxpalm {role} --help` lists every setting with its default",
        )
        return None
    report.add("config", PASS, f"{role} config valid ({report.source})")
    if role == "robot" and config.render.mode == "mask":
        try:
            from robot_side.perception import load_classifier

            clf = load_classifier(config.classifier.path, backend=config.classifier.backend)
            report.add("classifier", PASS, f"{clf.path.name} loads with backend {clf.backend}")
        except (DeepXPalmError, OSError, ValueError) as e:
            report.add(
                "classifier",
                FAIL,
                f"cannot load the CNN: {e}",
                "install the robot extra (pip install 'deepxpalm[robot]'), or fix "
                "robot.classifier.path / backend, or set robot.render.mode = 'direct'",
            )
    return config


# ------------------------------------------------------------------ processes
def _listener_pids(port: int) -> list[tuple[int, str]]:
    """Processes with a TCP socket listening on ``port``, from /proc/net/tcp{,6}."""
    inodes = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            cols = line.split()
            if len(cols) > 9 and cols[3] == "0A" and int(cols[1].rsplit(":", 1)[1], 16) == port:
                inodes.add(f"socket:[{cols[9]}]")
    return processes_holding(inodes, skip_self=False)


def _is_robot_node(command: str) -> bool:
    return ("deepxpalm" in command or "deploy.cli" in command) and " robot" in command


# ------------------------------------------------------------------- keys
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


def _check_keys(report: Report, role: str, security: Any, options: DoctorOptions) -> None:
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


# ---------------------------------------------------------------- devices
def _run_with_deadline(fn: Any, timeout_s: float) -> tuple[bool, Any]:
    """(finished, result or exception); a driver stuck past the deadline is left behind."""
    box: dict[str, Any] = {}

    def target() -> None:
        try:
            box["result"] = fn()
        except BaseException as e:
            box["error"] = e

    thread = threading.Thread(target=target, name="doctor-device", daemon=True)
    thread.start()
    thread.join(timeout_s)
    if thread.is_alive():
        return False, None
    if "error" in box:
        return True, box["error"]
    return True, box.get("result")


def _connect_status(device: Device) -> dict[str, Any]:
    device.connect()
    try:
        return device.status()
    finally:
        device.disconnect()


def _short_status(status: Any) -> str:
    if not isinstance(status, dict):
        return str(status)
    keep = {k: v for k, v in status.items() if not isinstance(v, (dict, list)) and k != "kind"}
    text = ", ".join(f"{k}={v}" for k, v in list(keep.items())[:6])
    return text or "connected"


def _check_devices(report: Report, role: str, config: Any, options: DoctorOptions) -> None:
    for family, module in FAMILIES[role]:
        where = f"{role}.{family}"
        section = dict(getattr(config, family))
        kind = section.get("kind", "none")
        name = f"device {where}"
        if kind == "none":
            report.add(name, SKIP, "not used (kind = 'none')")
            continue
        try:
            registry = importlib.import_module(module).KINDS
            device = build_device(registry, section, where)
        except DeepXPalmError as e:
            report.add(name, FAIL, str(e), f"fix [{where}]; `deepxpalm devices` shows the kinds")
            continue
        except ImportError as e:
            report.add(
                name,
                FAIL,
                f"kind {kind!r} cannot be imported: {e}",
                f"install this machine's extra: pip install 'deepxpalm[{role}]'",
            )
            continue
        findings = device.preflight(
            PreflightContext(
                where=where,
                tcp_timeout_s=options.tcp_timeout_s,
                service_user=options.service_user,
                service_groups=SERVICE_GROUPS,
            )
        )
        if findings:
            for finding in findings:
                report.add(name, finding.status, finding.detail, finding.fix)
            continue
        label = f"{kind} {device.location()}".rstrip()
        if not options.connect_devices:
            report.add(name, PASS, f"{label}: present (driver not opened: --no-connect)")
            continue
        finished, result = _run_with_deadline(
            lambda device=device: _connect_status(device), options.device_timeout_s
        )
        if not finished:
            report.add(
                name,
                FAIL,
                f"{label}: no answer within {options.device_timeout_s:.0f} s",
                "power, cabling, baud rate and the device's own mode (docs/bring-up.md, "
                "'When something does not answer')",
            )
        elif isinstance(result, BaseException):
            report.add(
                name,
                FAIL,
                f"{label}: {type(result).__name__}: {result}",
                "the driver's message names the cause; docs/bring-up.md, "
                "'When something does not answer'",
            )
        else:
            report.add(name, PASS, f"{label} answers: {_short_status(result)}")


# ---------------------------------------------------------------- network
def _host_port(endpoint: str) -> tuple[str, int] | None:
    if not endpoint.startswith("tcp://"):
        return None
    parts = urlsplit(endpoint)
    try:
        port = parts.port
    except ValueError:
        return None
    if port is None:
        return None
    return parts.hostname or "*", port


def _check_endpoints(report: Report, role: str, link: Any) -> None:
    from common.security import check_endpoint

    for endpoint in (link.telemetry_endpoint, link.command_endpoint):
        try:
            check_endpoint(endpoint, link.security)
        except DeepXPalmError as e:
            report.add(
                "link security",
                FAIL,
                str(e),
                f"set {role}.link.security.mode = 'curve' with keys (docs/deploy.md)",
            )
            return
    if link.security.mode == "curve":
        report.add("link security", PASS, "CURVE on both links")
    elif link.security.allow_insecure:
        report.add(
            "link security",
            WARN,
            "plain TCP off this machine (allow_insecure): anyone on the path reads and injects",
            f"set {role}.link.security.mode = 'curve'",
        )
    else:
        report.add("link security", PASS, "plain TCP, loopback only (no keys needed)")


class _Monitor:
    """Handshake events of one socket, read without blocking."""

    def __init__(self, sock: Any) -> None:
        self.sock = sock.get_monitor_socket()
        self.events: list[str] = []

    def poll(self) -> None:
        import zmq
        from zmq.utils.monitor import recv_monitor_message

        while True:
            try:
                msg = recv_monitor_message(self.sock, zmq.NOBLOCK)
            except zmq.Again:
                return
            try:
                self.events.append(zmq.Event(msg["event"]).name)
            except ValueError:
                self.events.append(str(msg["event"]))

    def has(self, name: str) -> bool:
        return name in self.events

    def close(self) -> None:
        self.sock.close(0)


@dataclass
class Exchange:
    """What a short heartbeat exchange with the other node saw."""

    heartbeats: int = 0
    stimuli: int = 0
    rejected: int = 0
    peer_state: str | None = None
    clock: ClockSync = field(default_factory=ClockSync)
    duration_s: float = 0.0
    sub_events: list[str] = field(default_factory=list)
    pub_events: list[str] = field(default_factory=list)
    denied_keys: list[str] = field(default_factory=list)


def heartbeat_exchange(
    ctx: Any,
    role: str,
    link: Any,
    timeout_s: float,
) -> Exchange:
    """Act as ``role``'s node for up to ``timeout_s``: send heartbeats, time the peer's.

    The robot side binds both ports with the node's own CURVE server options
    and allowlist; the operator side connects with its client options. Every
    heartbeat echoes the peer's newest one, so ``ClockSync`` gets NTP samples
    exactly as in the nodes. Raises ``zmq.ZMQError`` when a bind fails.
    """
    import zmq
    import zmq.auth  # common.security needs it loaded

    from common.codec import MAX_MESSAGE_BYTES, DecodeError, decode, encode
    from common.messages import Heartbeat, Stimulus
    from common.security import Authenticator, client_options, server_options

    out = Exchange()
    server = role == "robot"
    opts = server_options(link.security) if server else client_options(link.security)
    peer = "operator" if server else "robot"
    sockets: list[Any] = []
    monitors: list[_Monitor] = []
    with contextlib.ExitStack() as stack:
        if server:
            auth = Authenticator(ctx, link.security)
            stack.callback(auth.stop)
        pub = ctx.socket(zmq.PUB)
        sub = ctx.socket(zmq.SUB)
        for sock in (pub, sub):
            sockets.append(sock)
            sock.setsockopt(zmq.LINGER, 0)
            for opt, value in opts.items():
                sock.setsockopt(opt, value)
        stack.callback(lambda: [s.close(0) for s in sockets])
        sub.setsockopt(zmq.MAXMSGSIZE, MAX_MESSAGE_BYTES)
        sub.setsockopt(zmq.SUBSCRIBE, b"")
        pub_mon, sub_mon = _Monitor(pub), _Monitor(sub)
        monitors += [pub_mon, sub_mon]
        stack.callback(lambda: [m.close() for m in monitors])
        pub_ep = link.telemetry_endpoint if server else link.command_endpoint
        sub_ep = link.command_endpoint if server else link.telemetry_endpoint
        if server:
            pub.bind(pub_ep)
            sub.bind(sub_ep)
        else:
            sub.connect(sub_ep)
            pub.connect(pub_ep)
        poller = zmq.Poller()
        poller.register(sub, zmq.POLLIN)
        seq = 0
        t0 = time.monotonic()
        next_hb = t0
        while time.monotonic() - t0 < timeout_s and out.clock.accepted < CLOCK_SAMPLES:
            now = time.monotonic()
            if now >= next_hb:
                seq += 1
                echo_send, echo_recv = out.clock.echo_fields()
                pub.send(
                    encode(
                        Heartbeat(
                            seq=seq,
                            t_send_ns=now_ns(),
                            node=role,
                            state="ok" if out.heartbeats else "down",
                            echo_t_send_ns=echo_send,
                            echo_t_recv_ns=echo_recv,
                            stats={"doctor": 1.0},
                        )
                    ),
                    zmq.NOBLOCK,
                )
                next_hb = now + HEARTBEAT_PERIOD_S
            if poller.poll(max(1, int((next_hb - time.monotonic()) * 1000))):
                while True:
                    try:
                        data = sub.recv(zmq.NOBLOCK)
                    except zmq.Again:
                        break
                    t_recv = now_ns()
                    try:
                        msg = decode(data)
                    except DecodeError:
                        out.rejected += 1
                        continue
                    if isinstance(msg, Heartbeat) and msg.node == peer:
                        out.heartbeats += 1
                        out.peer_state = msg.state
                        out.clock.on_heartbeat(
                            msg.t_send_ns, msg.echo_t_send_ns, msg.echo_t_recv_ns, t_recv
                        )
                    elif isinstance(msg, Stimulus):
                        out.stimuli += 1
            for m in monitors:
                m.poll()
        out.duration_s = time.monotonic() - t0
        for m in monitors:
            m.poll()
        out.pub_events, out.sub_events = pub_mon.events, sub_mon.events
        out.denied_keys = auth.refused_keys if server else []
    return out


def _clock_verdict(report: Report, role: str, config: Any, ex: Exchange) -> None:
    est = ex.clock.estimate()
    if est is None:
        report.add(
            "clock",
            FAIL,
            f"{ex.heartbeats} heartbeats from the {'operator' if role == 'robot' else 'robot'} "
            "but none echoed ours: it does not hear this side",
            "the link works one way only: check the firewall for the command port "
            "(5556/tcp) and that both ends use the same ports",
        )
        return
    rtt_ms = est.delay_ns / 1e6
    if role == "operator":
        limit_ms, limit_name = config.link.stale_after_ms, "operator.link.stale_after_ms"
    else:  # commands are judged on the operator's send time: both limits must cover the path
        limit_ms, limit_name = min(
            (config.link.deadman_ms, "robot.link.deadman_ms"),
            (config.link.max_command_age_ms, "robot.link.max_command_age_ms"),
        )
    detail = (
        f"offset {est.offset_ns / 1e9:+.6f} s (peer's monotonic clock minus ours; any value "
        f"is fine, boot times differ) +- {est.uncertainty_ns / 1e6:.2f} ms; round trip "
        f"{rtt_ms:.2f} ms (best of {est.samples})"
    )
    one_way = rtt_ms / 2
    if one_way >= limit_ms:
        report.add(
            "clock",
            FAIL,
            f"{detail}: one way ({one_way:.0f} ms) exceeds {limit_name} = {limit_ms:.0f} ms, "
            "so nothing will ever be fresh",
            f"use a faster path, or raise {limit_name} knowing the palm then feels old contact",
        )
    elif one_way > limit_ms / 2:
        report.add(
            "clock",
            WARN,
            f"{detail}: one way ({one_way:.0f} ms) is over half of {limit_name} "
            f"({limit_ms:.0f} ms); jitter will make stimuli stale",
            f"find the slow hop (mtr to the peer), or raise {limit_name}",
        )
    else:
        report.add("clock", PASS, detail)


def _check_robot_link(report: Report, config: Any, options: DoctorOptions) -> bool:
    """Ports bindable, and an operator heard if one runs. False if the robot node is running."""
    import zmq

    link = config.link
    endpoints = [link.telemetry_endpoint, link.command_endpoint]
    # Who holds the ports already? The node itself (fine, but then skip), or a stranger.
    for endpoint in endpoints:
        hp = _host_port(endpoint)
        if hp is None:
            continue
        holders = _listener_pids(hp[1])
        robots = [h for h in holders if _is_robot_node(h[1]) and h[0] != os.getpid()]
        if robots:
            pid, cmd = robots[0]
            report.add(
                "robot ports",
                WARN,
                f"the robot node is already running (pid {pid}: {cmd[:80]}) and holds "
                f"{endpoint}: device and port checks skipped",
                "for a full check stop it first: `sudo systemctl stop deepxpalm-robot`",
            )
            return False
    if not options.check_peer:
        report.add("robot ports", SKIP, "not checked (--no-peer)")
        return True
    ctx = zmq.Context()
    try:
        try:
            ex = heartbeat_exchange(ctx, "robot", link, options.peer_timeout_s)
        except zmq.ZMQError as e:
            _bind_failure(report, endpoints, e)
            return True
        except DeepXPalmError as e:
            report.add("robot ports", FAIL, str(e), "fix the keys above first")
            return True
    finally:
        ctx.destroy(linger=0)
    report.add("robot ports", PASS, f"{' and '.join(endpoints)} bind with the node's options")
    if ex.denied_keys:
        report.add(
            "peer operator",
            FAIL,
            "an operator tried to connect with a key this robot does not allow: "
            + ", ".join(ex.denied_keys),
            "if that operator is legitimate: copy its NAME.key here and `deepxpalm keys allow "
            f"NAME.key --authorized {link.security.authorized_keys_dir}`; restart the node",
        )
    elif ex.heartbeats == 0:
        failed = [e for e in ex.sub_events + ex.pub_events if e.startswith("HANDSHAKE_FAILED")]
        if failed:
            report.add(
                "peer operator",
                FAIL,
                f"operators tried to connect but the CURVE handshake failed ({failed[0]}): "
                "they hold a different robot public key",
                "copy this robot's public key (robot.key next to the secret) to the operator "
                "PC's server_public_key_file",
            )
        else:
            report.add(
                "peer operator",
                WARN,
                f"no operator connected within {ex.duration_s:.1f} s (not running yet, or it "
                "cannot reach this PC)",
                "start the operator node and re-run to measure the clock offset; on the "
                "operator PC `deepxpalm doctor --role operator` tests the path from there",
            )
    else:
        report.add(
            "peer operator",
            PASS,
            f"operator node answers: {ex.heartbeats} heartbeats in {ex.duration_s:.1f} s",
        )
        _clock_verdict(report, "robot", config, ex)
    return True


def _bind_failure(report: Report, endpoints: list[str], e: Any) -> None:
    detail = f"cannot bind {' / '.join(endpoints)}: {e.strerror}"
    if e.errno == errno.EADDRINUSE:
        holders = []
        for endpoint in endpoints:
            hp = _host_port(endpoint)
            holders += _listener_pids(hp[1]) if hp else []
        who = f" (pid {holders[0][0]}: {holders[0][1][:60]})" if holders else ""
        report.add(
            "robot ports",
            FAIL,
            f"{detail}: another process holds the port{who}",
            "stop that process, or move robot.link.*_endpoint (and the operator's) to free "
            "ports; `ss -ltnp` shows who listens",
        )
    elif e.errno == errno.EADDRNOTAVAIL:
        report.add(
            "robot ports",
            FAIL,
            f"{detail}: that address is not one of this machine's",
            "use tcp://*:PORT or an address from `ip -brief addr`",
        )
    else:
        report.add(
            "robot ports",
            FAIL,
            detail,
            "ports below 1024 need root; use the defaults 5555/5556",
        )


def _check_operator_link(report: Report, config: Any, options: DoctorOptions) -> None:
    import zmq

    link = config.link
    if not options.check_peer:
        report.add("peer robot", SKIP, "not checked (--no-peer)")
        return
    for endpoint in (link.telemetry_endpoint, link.command_endpoint):
        hp = _host_port(endpoint)
        if hp is None:
            continue
        problem = tcp_probe(hp[0], hp[1], options.tcp_timeout_s)
        if problem is not None:
            refused = "refused" in problem
            report.add(
                "peer robot",
                FAIL,
                f"robot unreachable at {endpoint}: {problem}",
                (
                    "start the robot node on the robot PC (`sudo systemctl status "
                    "deepxpalm-robot`) and check that operator.link endpoints match its "
                    f"ports; a firewall rejecting {hp[1]}/tcp looks the same"
                    if refused
                    else f"check the address and the VPN (`ping {hp[0]}`), and that the "
                    f"robot PC's firewall lets {hp[1]}/tcp in (`sudo ufw allow 5555:5556/tcp`)"
                ),
            )
            return
    ctx = zmq.Context()
    try:
        try:
            ex = heartbeat_exchange(ctx, "operator", link, options.peer_timeout_s)
        except DeepXPalmError as e:
            report.add("peer robot", FAIL, str(e), "fix the keys above first")
            return
    finally:
        ctx.destroy(linger=0)
    events = ex.sub_events + ex.pub_events
    if "HANDSHAKE_FAILED_AUTH" in events:
        public = link.security.secret_key_file
        report.add(
            "peer robot",
            FAIL,
            "the robot refused this operator's key (CURVE ZAP: not in its allowlist)",
            f"copy this operator's public key ({Path(str(public)).with_suffix('.key').name} "
            "next to its secret) to the robot PC and `deepxpalm keys allow NAME.key "
            "--authorized /etc/deepxpalm/keys/operators`; restart the robot node",
        )
        return
    if ex.heartbeats == 0 and any(e.startswith("HANDSHAKE_FAILED") for e in events):
        failed = next(e for e in events if e.startswith("HANDSHAKE_FAILED"))
        report.add(
            "peer robot",
            FAIL,
            f"the CURVE handshake with the robot failed ({failed}): "
            f"{link.security.server_public_key_file} is not the key the robot holds"
            + ("" if link.security.mode == "curve" else ", or one side runs plain"),
            "compare `deepxpalm keys show` of the robot's robot.key on both machines and "
            "copy it again; both nodes must use the same security.mode",
        )
        return
    if ex.heartbeats == 0:
        report.add(
            "peer robot",
            FAIL,
            f"the robot's ports accept connections but no heartbeat came in "
            f"{ex.duration_s:.1f} s"
            + (f" ({ex.rejected} rejected: another protocol version?)" if ex.rejected else "")
            + ": not a DeepXPalm robot node, or one side runs CURVE and the other plain",
            "check what listens there on the robot PC (`ss -ltnp`) and that both configs use "
            "the same security.mode",
        )
        return
    report.add(
        "peer robot",
        PASS,
        f"robot node answers over {'CURVE' if link.security.mode == 'curve' else 'plain TCP'}: "
        f"{ex.heartbeats} heartbeats, {ex.stimuli} stimuli in {ex.duration_s:.1f} s; it sees "
        f"the link as {ex.peer_state!r}",
    )
    _clock_verdict(report, "operator", config, ex)


# ----------------------------------------------------------------- system
def _check_governor(report: Report) -> None:
    files = sorted(glob.glob("/sys/devices/system/cpu/cpu[0-9]*/cpufreq/scaling_governor"))
    if not files:
        report.add(
            "cpu governor",
            SKIP,
            "no cpufreq interface (a VM, or a CPU at a fixed clock): nothing to set",
        )
        return
    governors: dict[str, list[str]] = {}
    for f in files:
        try:
            g = Path(f).read_text().strip()
        except OSError:
            continue
        governors.setdefault(g, []).append(f.split("/")[5])
    if set(governors) == {"performance"}:
        report.add("cpu governor", PASS, f"performance on all {len(files)} CPUs")
        return
    summary = "; ".join(f"{g} on {len(c)} CPU(s)" for g, c in governors.items())
    report.add(
        "cpu governor",
        WARN,
        f"{summary}: clock ramps add latency jitter to a 60 Hz loop",
        "`sudo cpupower frequency-set -g performance` (package linux-cpupower), made "
        "permanent as in docs/deploy.md",
    )


def _can_use_fifo() -> tuple[bool, str]:
    """Try SCHED_FIFO priority 1 on a throwaway thread (the policy is per thread on Linux)."""
    result: dict[str, Any] = {}

    def probe() -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
            result["ok"] = True
        except OSError as e:
            result["ok"], result["why"] = False, e.strerror or str(e)

    t = threading.Thread(target=probe, name="doctor-rt-probe", daemon=True)
    t.start()
    t.join(2)
    return bool(result.get("ok")), result.get("why", "")


def _check_realtime(report: Report) -> None:
    import resource

    if not hasattr(os, "SCHED_FIFO"):
        report.add("real-time scheduling", SKIP, "this platform has no SCHED_FIFO")
        return
    max_prio = os.sched_get_priority_max(os.SCHED_FIFO)
    soft, _hard = resource.getrlimit(resource.RLIMIT_RTPRIO)
    ok, why = _can_use_fifo()
    kernel = "PREEMPT_RT" if Path("/sys/kernel/realtime").exists() else os.uname().version
    rt_kernel = "PREEMPT_RT" in kernel
    try:
        runtime = int(Path("/proc/sys/kernel/sched_rt_runtime_us").read_text())
    except (OSError, ValueError):
        runtime = None
    rlimit = "unlimited" if soft == resource.RLIM_INFINITY else str(soft)
    detail = (
        f"SCHED_FIFO priorities 1..{max_prio}, RLIMIT_RTPRIO {rlimit}, "
        f"{'PREEMPT_RT kernel' if rt_kernel else 'standard kernel'}"
        + (f", RT throttling {runtime} us/s" if runtime is not None else "")
    )
    if ok:
        report.add("real-time scheduling", PASS, f"{detail}: this user can use SCHED_FIFO")
    else:
        report.add(
            "real-time scheduling",
            WARN,
            f"{detail}: this user cannot use SCHED_FIFO ({why}); the units run with Nice=-10",
            "only needed for the real-time drop-in in docs/deploy.md (systemd sets the policy "
            "itself); for a shell session add '@dialout - rtprio 50' to "
            "/etc/security/limits.d/deepxpalm.conf",
        )


def _check_service_user(report: Report, options: DoctorOptions) -> None:
    user = user_named(options.service_user)
    if user is None:
        report.add(
            "service user",
            SKIP,
            f"no user {options.service_user!r} (only the systemd units need it; "
            "deploy/systemd/deepxpalm.sysusers.conf makes it)",
        )
        return
    report.add(
        "service user",
        PASS,
        f"{options.service_user} exists (uid {user.pw_uid}); the units add dialout",
    )


# -------------------------------------------------------------------- main
def diagnose(
    role: str, data: dict[str, Any], source: str, options: DoctorOptions | None = None
) -> Report:
    """Every check for ``role`` on a node config table (already picked from the file)."""
    options = options or DoctorOptions()
    report = Report(role, source)
    config = _check_config(report, role, data)
    if config is None:
        return report
    _check_endpoints(report, role, config.link)
    _check_keys(report, role, config.link.security, options)
    keys_failed = any(c.name.startswith("keys") and c.status == FAIL for c in report.checks)
    node_running = False
    if role == "robot":
        if keys_failed:
            report.add("robot ports", SKIP, "not checked: the keys above fail")
        else:
            node_running = not _check_robot_link(report, config, options)
    if node_running:
        report.add("devices", SKIP, "the robot node owns them")
    else:
        _check_devices(report, role, config, options)
    if role == "operator":
        if keys_failed:
            report.add("peer robot", SKIP, "not checked: the keys above fail")
        else:
            _check_operator_link(report, config, options)
    _check_governor(report)
    _check_realtime(report)
    _check_service_user(report, options)
    return report


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = __doc__
    parser.add_argument(
        "--config",
        "--scene",
        dest="config",
        help="node config or scene: a TOML path or a shipped scene name "
        "(default /etc/deepxpalm/ROLE.toml)",
    )
    parser.add_argument(
        "--role", choices=ROLES, help="which node this machine runs (default: the file's only one)"
    )
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a setting, e.g. --set robot.tactile.port=/dev/ttyUSB1 (repeatable)",
    )
    parser.add_argument("--json", action="store_true", help="print one JSON report")
    parser.add_argument(
        "--device-timeout", type=float, default=5.0, help="seconds per device (default 5)"
    )
    parser.add_argument(
        "--peer-timeout",
        type=float,
        default=3.0,
        help="seconds to wait for the other node's heartbeats (default 3)",
    )
    parser.add_argument(
        "--no-connect",
        action="store_true",
        help="check that devices are present and reachable without opening their drivers",
    )
    parser.add_argument(
        "--no-peer", action="store_true", help="skip the ports and the other node's heartbeats"
    )


def _resolve(args: argparse.Namespace) -> tuple[str, dict[str, Any], str]:
    """(role, that node's table with overrides, where it came from)."""
    from deploy.scene import scene_path

    source = args.config
    if source is None:
        if args.role is None:
            raise ConfigError("give --config FILE (or --scene NAME) and/or --role robot|operator")
        source = f"/etc/deepxpalm/{args.role}.toml"
    path = scene_path(source)
    data = load_toml(path)
    role = args.role or infer_role(data)
    if role is None:
        raise ConfigError(
            f"{path} configures {'both nodes' if 'robot' in data else 'no node table'}: "
            "pass --role robot or --role operator"
        )
    prefix = f"{role}."
    local = [o[len(prefix) :] if o.startswith(prefix) else o for o in args.overrides]
    return role, apply_overrides(node_section(data, role), local), str(path)


def run(args: argparse.Namespace) -> int:
    options = DoctorOptions(
        device_timeout_s=args.device_timeout,
        peer_timeout_s=args.peer_timeout,
        connect_devices=not args.no_connect,
        check_peer=not args.no_peer,
    )
    try:
        role, data, source = _resolve(args)
    except ConfigError as e:
        role = args.role or "?"
        default = f"/etc/deepxpalm/{role}.toml"
        report = Report(role, args.config or default)
        report.add(
            "config",
            FAIL,
            str(e),
            f"copy deploy/config/{role}.toml to {default} and edit its LAB lines, or give "
            "--config FILE / --scene NAME"
            if args.config is None and args.role
            else "give a config file or shipped scene name that exists and parses, and --role",
        )
    else:
        report = diagnose(role, data, source, options)
    if args.json:
        print(json.dumps(report.to_dict(), indent=2))
    else:
        print(report.to_text())
    sys.stdout.flush()
    return 0 if report.ok else 1


__all__ = ["Check", "DoctorOptions", "Report", "diagnose", "heartbeat_exchange", "run"]
