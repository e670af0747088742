"""The configured devices: each one's own preflight findings, then its driver, with a deadline."""

from __future__ import annotations

import importlib
import threading
from typing import Any

from common.devices.lifecycle import Device, build_device
from common.devices.preflight import FAIL, PASS, SKIP, PreflightContext
from common.errors import DeepXPalmError
from deploy.doctor.report import SERVICE_GROUPS, DoctorOptions, Report

#: (family in the node config, registry module), per role.
FAMILIES = {
    "robot": (
        ("tactile", "robot_side.tactile"),
        ("gripper", "robot_side.gripper"),
        ("arm", "robot_side.arm"),
    ),
    "operator": (("servos", "operator_side.servos"),),
}


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


def check_devices(report: Report, role: str, config: Any, options: DoctorOptions) -> None:
    """Each configured device: its own preflight first, so a missing port is named as one."""
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
