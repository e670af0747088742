"""`deepxpalm devices` says which device fails and why, in words a user can act on."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

pytestmark = pytest.mark.slow


def devices(*sets: str, role: str = "both") -> tuple[int, list[dict]]:
    args = [sys.executable, "-m", "deploy.cli", "devices", "--json", "--role", role]
    for s in sets:
        args += ["--set", s]
    out = subprocess.run(args, capture_output=True, text=True, timeout=60)
    return out.returncode, json.loads(out.stdout)


def by_device(report: list[dict]) -> dict[str, dict]:
    return {e["device"]: e for e in report}


def test_demo_scene_devices_all_answer():
    code, report = devices()
    assert code == 0, report
    assert all(e["ok"] for e in report)


def test_wire_level_simulators_answer_through_the_real_drivers():
    code, report = devices(
        'robot.tactile={kind="simulated_serial"}', 'operator.servos={kind="simulated_feetech"}'
    )
    assert code == 0, report
    assert by_device(report)["robot.tactile"]["state"]["frames"] >= 1


def test_missing_port_is_named():
    code, report = devices('robot.tactile={kind="serial", port="/dev/ttyDEEPXPALM9"}', role="robot")
    assert code == 1
    error = by_device(report)["robot.tactile"]["error"]
    assert "/dev/ttyDEEPXPALM9 does not exist" in error and "by-id" in error


def test_wrong_baud_rate_is_diagnosed():
    code, report = devices(
        'robot.tactile={kind="simulated_serial", driver={baudrate=115200}}', role="robot"
    )
    assert code == 1
    assert "wrong baud rate" in by_device(report)["robot.tactile"]["error"]


def test_a_port_with_nothing_answering_is_reported():
    master, slave = os.openpty()
    try:
        code, report = devices(
            f'operator.servos={{kind="feetech", port="{os.ttyname(slave)}"}}', role="operator"
        )
    finally:
        os.close(master)
        os.close(slave)
    assert code == 1
    error = by_device(report)["operator.servos"]["error"].lower()
    assert "answer" in error or "respond" in error, error
