"""``deepxpalm doctor``: is this machine ready for a session? A pass/warn/fail list.

    deepxpalm doctor --role robot --config /etc/deepxpalm/robot.toml
    deepxpalm doctor --role operator --config /etc/deepxpalm/operator.toml
    deepxpalm doctor --role router --config /etc/deepxpalm/router.toml
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
import json
import sys
from typing import Any

from common.config.overrides import apply_overrides
from common.config.typed import load_toml
from common.devices.preflight import FAIL, SKIP
from common.errors import ConfigError
from common.process.command_line import add_overrides_argument
from deploy.doctor.devices import check_devices
from deploy.doctor.keys import check_keys
from deploy.doctor.link import check_endpoints, check_operator_link, check_robot_link
from deploy.doctor.node_config import check_config, infer_role, node_section
from deploy.doctor.report import ROLES, DoctorOptions, Report
from deploy.doctor.system import check_governor, check_realtime, check_service_user
from deploy.doctor.video import check_video


def diagnose(
    role: str, data: dict[str, Any], source: str, options: DoctorOptions | None = None
) -> Report:
    """Every check for ``role`` on a node config table (already picked from the file)."""
    options = options or DoctorOptions()
    report = Report(role, source)
    if role == "router":
        from deploy.doctor.router import diagnose_router

        diagnose_router(report, data, options)
        check_service_user(report, options)
        return report
    config = check_config(report, role, data)
    if config is None:
        return report
    if config.link.mode == "fabric":
        return _diagnose_fabric(report, role, config, options)
    check_endpoints(report, role, config.link)
    check_keys(report, role, config.link.security, options)
    keys_failed = any(c.name.startswith("keys") and c.status == FAIL for c in report.checks)
    node_running = False
    if role == "robot":
        if keys_failed:
            report.add("robot ports", SKIP, "not checked: the keys above fail")
        else:
            node_running = not check_robot_link(report, config, options)
    if node_running:
        report.add("devices", SKIP, "the robot node owns them")
    else:
        check_devices(report, role, config, options)
    if role == "robot":
        check_video(report, config, options)
    if role == "operator":
        if keys_failed:
            report.add("peer robot", SKIP, "not checked: the keys above fail")
        else:
            check_operator_link(report, config, options)
    check_governor(report)
    check_realtime(report, config, role, options.keep_alive_probe_s)
    check_service_user(report, options)
    return report


def _diagnose_fabric(report: Report, role: str, config: Any, options: DoctorOptions) -> Report:
    """A node on the fabric: its certificate and router instead of endpoints and CURVE keys."""
    from deploy.doctor.fabric import check_fabric

    check_fabric(report, role, config, options)
    check_devices(report, role, config, options)
    if role == "robot":
        check_video(report, config, options)
    check_governor(report)
    check_realtime(report, config, role, options.keep_alive_probe_s)
    check_service_user(report, options)
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
    add_overrides_argument(parser, "robot.tactile.port=/dev/ttyUSB1")
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
    parser.add_argument(
        "--keep-alive-probe",
        type=float,
        default=DoctorOptions.keep_alive_probe_s,
        metavar="SECONDS",
        help="how long the robot's real-time probe wakes as the arm's keep-alive does "
        "(default %(default)s; 0 skips it)",
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
        keep_alive_probe_s=args.keep_alive_probe,
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
