"""``deepxpalm devices``: what a scene's devices are, and whether each one answers.

Each device named in the scene is built, connected, asked for its status and
disconnected, one at a time; a device that fails says why in the driver's
own words (a missing port, a wrong baud rate, no answer), and the command
exits non-zero.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from common.devices.lifecycle import build_device
from common.errors import DeepXPalmError
from common.process.command_line import add_overrides_argument
from deploy.scene import load_scene_dict


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", default="demo", help="shipped scene name or TOML path")
    parser.add_argument("--role", choices=("robot", "operator", "both"), default="both")
    parser.add_argument("--json", action="store_true", help="print one JSON report")
    add_overrides_argument(parser, "robot.tactile.port=/dev/ttyUSB1")


def _registries(role: str) -> list[tuple[str, str, str]]:
    """(role, family key in the node's config, registry module)."""
    out = []
    if role in ("robot", "both"):
        out += [
            ("robot", "tactile", "robot_side.tactile"),
            ("robot", "gripper", "robot_side.gripper"),
            ("robot", "arm", "robot_side.arm"),
        ]
    if role in ("operator", "both"):
        out.append(("operator", "servos", "operator_side.servos"))
    return out


def check_devices(data: dict[str, Any], role: str) -> list[dict[str, Any]]:
    import importlib

    report = []
    for node, family, module in _registries(role):
        section = dict((data.get(node) or {}).get(family) or {})
        kind = section.get("kind", "scripted" if family == "tactile" else "none")
        if family == "servos":
            kind = section.get("kind", "in_memory")
        section["kind"] = kind
        entry: dict[str, Any] = {"device": f"{node}.{family}", "kind": kind}
        if kind == "none":
            entry.update(ok=True, state="not used in this scene")
            report.append(entry)
            continue
        try:
            registry = importlib.import_module(module).KINDS
            device = build_device(registry, section, f"{node}.{family}")
            device.connect()
            try:
                entry.update(ok=True, state=device.status())
            finally:
                device.disconnect()
        except DeepXPalmError as e:
            entry.update(ok=False, error=f"{type(e).__name__}: {e}")
        except Exception as e:  # a driver bug must still be reported per device
            entry.update(ok=False, error=f"unexpected {type(e).__name__}: {e}")
        report.append(entry)
    return report


def run(args: argparse.Namespace) -> int:
    data = load_scene_dict(args.scene, args.overrides)
    report = check_devices(data, args.role)
    if args.json:
        print(json.dumps(report, indent=2, default=str))
    else:
        for entry in report:
            mark = "ok  " if entry["ok"] else "FAIL"
            detail = entry.get("error") or entry.get("state")
            print(f"[{mark}] {entry['device']:<18} {entry['kind']:<18} {detail}", file=sys.stdout)
    return 0 if all(e["ok"] for e in report) else 1
