"""The link: endpoints and security, the other node's heartbeats, the clock between them.

The exchange of heartbeats itself is ``deploy.doctor.exchange``'s; this
module judges what it saw.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from common.devices.preflight import FAIL, PASS, SKIP, WARN, processes_holding, tcp_probe
from common.errors import DeepXPalmError
from deploy.doctor.exchange import Exchange, heartbeat_exchange
from deploy.doctor.report import DoctorOptions, Report


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


def check_endpoints(report: Report, role: str, link: Any) -> None:
    """Refuse plain TCP off this machine, as the node itself would."""
    from common.keys.curve import check_endpoint

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


def link_health_verdict(report: Report, peer: str, stats: dict[str, float]) -> None:
    """The peer's own view of its links (each end it connects out with up, and how often it
    was opened again), from its heartbeat's counters."""
    ends = [e for e in ("telemetry", "commands", "fabric_router") if f"link_{e}_up" in stats]
    if not ends:
        return  # a direct link: the node binds, nothing to reopen
    down = [e for e in ends if not stats[f"link_{e}_up"]]
    reopened = {e: int(stats.get(f"link_{e}_reopened", 0)) for e in ends}
    detail = ", ".join(
        f"{e} {'down' if e in down else 'up'}"
        + (f" (opened again {reopened[e]}x)" if reopened[e] else "")
        for e in ends
    )
    if down:
        report.add(
            f"{peer} links",
            WARN,
            f"the {peer} node reports its {' and '.join(down)} link down: {detail}",
            "it reopens a link by itself within 2 s; if it stays down, check the path "
            f"(on the fabric: `deepxpalm doctor --role router` on the router host) and the "
            f"{peer} node's log for 'link ... opened again'",
        )
    else:
        report.add(f"{peer} links", PASS, f"the {peer} node's links: {detail}")


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


def check_robot_link(report: Report, config: Any, options: DoctorOptions) -> bool:
    """Ports bindable, and an operator heard if one runs. False if the robot node is running."""
    import zmq

    link_cfg = config.link
    endpoints = [link_cfg.telemetry_endpoint, link_cfg.command_endpoint]
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
            ex = heartbeat_exchange(ctx, "robot", link_cfg, options.peer_timeout_s)
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
            f"NAME.key --authorized {link_cfg.security.authorized_keys_dir}`; restart the node",
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
        link_health_verdict(report, "operator", ex.peer_stats)
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


def check_operator_link(report: Report, config: Any, options: DoctorOptions) -> None:
    """Reach the robot's ports, then talk to it with this operator's own keys and options."""
    import zmq

    link_cfg = config.link
    if not options.check_peer:
        report.add("peer robot", SKIP, "not checked (--no-peer)")
        return
    for endpoint in (link_cfg.telemetry_endpoint, link_cfg.command_endpoint):
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
            ex = heartbeat_exchange(ctx, "operator", link_cfg, options.peer_timeout_s)
        except DeepXPalmError as e:
            report.add("peer robot", FAIL, str(e), "fix the keys above first")
            return
    finally:
        ctx.destroy(linger=0)
    events = ex.sub_events + ex.pub_events
    if "HANDSHAKE_FAILED_AUTH" in events:
        public = link_cfg.security.secret_key_file
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
            f"{link_cfg.security.server_public_key_file} is not the key the robot holds"
            + ("" if link_cfg.security.mode == "curve" else ", or one side runs plain"),
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
        f"robot node answers over {'CURVE' if link_cfg.security.mode == 'curve' else 'plain TCP'}: "
        f"{ex.heartbeats} heartbeats, {ex.stimuli} stimuli in {ex.duration_s:.1f} s; it sees "
        f"the link as {ex.peer_state!r}",
    )
    link_health_verdict(report, "robot", ex.peer_stats)
    _clock_verdict(report, "operator", config, ex)
