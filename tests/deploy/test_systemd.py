"""The systemd units verify, run what the example configs expect, and the udev rules parse."""

from __future__ import annotations

import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from deploy_support import ENV, EXAMPLES, REPO
from tests_support import wait_until

UNITS = REPO / "deploy" / "systemd"
RULES = REPO / "deploy" / "udev" / "99-deepxpalm.rules"
ROLES = ("robot", "operator")
#: every unit shipped: the two nodes', the router's and the robot PC's camera server
UNITS_SHIPPED = (*ROLES, "router", "video")
INSTALLED = "/opt/deepxpalm/.venv/bin/deepxpalm"


def _unit(role: str) -> Path:
    return UNITS / f"deepxpalm-{role}.service"


def _parse(path: Path) -> dict[str, list[tuple[str, str]]]:
    """Sections -> (key, value) in order; systemd allows a key more than once."""
    sections: dict[str, list[tuple[str, str]]] = {}
    current = None
    for raw in path.read_text().splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("["):
            current = sections.setdefault(line.strip("[]"), [])
            continue
        key, _, value = line.partition("=")
        assert current is not None, f"{path.name}: {line!r} before any section"
        current.append((key.strip(), value.strip()))
    return sections


def _get(unit: dict, section: str, key: str) -> list[str]:
    return [v for k, v in unit[section] if k == key]


def _deepxpalm_here() -> str:
    """This environment's deepxpalm entry point, for ExecStart in a verified copy."""
    candidate = Path(sys.executable).with_name("deepxpalm")
    if candidate.exists():
        return str(candidate)
    found = shutil.which("deepxpalm")
    if found is None:
        pytest.skip("no deepxpalm entry point installed here")
    return found


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="no systemd-analyze here")
@pytest.mark.parametrize("role", UNITS_SHIPPED)
def test_unit_passes_systemd_analyze_verify(role, tmp_path):
    # verify checks that ExecStart's binary exists: point it at this environment's.
    text = _unit(role).read_text().replace(INSTALLED, _deepxpalm_here())
    copy = tmp_path / _unit(role).name
    copy.write_text(text)
    out = subprocess.run(
        ["systemd-analyze", "verify", "--man=no", str(copy)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 0, out.stderr
    # Unknown or misspelt keys are only warnings ("Unknown key ..., ignoring"): refuse them too.
    assert out.stderr.strip() == "", out.stderr


@pytest.mark.parametrize("role", ROLES)
def test_unit_is_a_watched_restarting_service_of_the_dedicated_user(role):
    unit = _parse(_unit(role))
    assert _get(unit, "Service", "Type") == ["notify"]
    assert _get(unit, "Service", "NotifyAccess") == ["main"]
    # the operator's palm is pressed while its node is frozen: ended sooner (docs/robustness.md)
    assert _get(unit, "Service", "WatchdogSec") == (["2s"] if role == "operator" else ["5s"])
    assert _get(unit, "Service", "Restart") == ["on-failure"]
    assert _get(unit, "Unit", "StartLimitIntervalSec") == ["0"]  # never give up
    assert _get(unit, "Service", "User") == ["deepxpalm"]
    assert _get(unit, "Service", "SupplementaryGroups") == ["dialout"]
    assert _get(unit, "Service", "StandardError") == ["journal"]
    assert _get(unit, "Service", "SyslogIdentifier") == [f"deepxpalm-{role}"]
    assert _get(unit, "Service", "Nice") == ["-10"]
    assert _get(unit, "Service", "RestrictRealtime") == []  # the real-time drop-in must work
    assert "After" in dict(unit["Unit"]) and "network-online.target" in _get(unit, "Unit", "After")
    assert _get(unit, "Install", "WantedBy") == ["multi-user.target"]


def _print_config(role: str, argv: list[str], tmp_path: Path) -> subprocess.CompletedProcess:
    """The unit's command line, the example config standing in for /etc, with --print-config."""
    args = [
        str(EXAMPLES / f"{role}.toml")
        if a == f"/etc/deepxpalm/{role}.toml"
        else str(tmp_path / Path(a).name)
        if a.startswith("/var/lib/deepxpalm/")
        else a
        for a in argv[1:]
    ]
    return subprocess.run(
        [sys.executable, "-m", "deploy.cli", *args, "--print-config"],
        capture_output=True,
        text=True,
        timeout=60,
        env=ENV,
    )


def _config_the_unit_starts(unit: dict, role: str, tmp_path: Path) -> str:
    """The unit's ExecStart, with the example config standing in for /etc, run to --print-config.

    The installed entry point and the /etc config are asserted on the way; the
    printed config is returned for the caller's own checks.
    """
    (exec_start,) = _get(unit, "Service", "ExecStart")
    argv = shlex.split(exec_start)
    assert argv[0] == INSTALLED
    assert f"/etc/deepxpalm/{role}.toml" in argv
    out = _print_config(role, argv, tmp_path)
    assert out.returncode == 0, out.stderr
    return out.stdout


@pytest.mark.slow
@pytest.mark.parametrize("role", ROLES)
def test_execstart_is_a_command_line_the_node_accepts(role, tmp_path):
    # The same arguments, with the example config standing in for /etc, parse and load.
    printed = _config_the_unit_starts(_parse(_unit(role)), role, tmp_path)
    assert f"[{role}]" in printed


def test_sysusers_makes_the_units_user_in_dialout():
    lines = [
        line.split()
        for line in (UNITS / "deepxpalm.sysusers.conf").read_text().splitlines()
        if line.strip() and not line.startswith("#")
    ]
    assert lines[0][:3] == ["u", "deepxpalm", "-"]
    assert ["m", "deepxpalm", "dialout"] in lines


RULE_TOKEN = re.compile(r'^\s*([A-Z_]+)(\{[^}]+\})?\s*(==|!=|\+=|-=|:=|=)\s*"([^"]*)"\s*$')


def _rules() -> list[list[tuple[str, str, str]]]:
    rules = []
    for raw in RULES.read_text().splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        parsed = []
        for token in line.split(", "):
            m = RULE_TOKEN.match(token)
            assert m, f"cannot parse {token!r} in {line!r}"
            key, attr, op, value = m.groups()
            parsed.append((key + (attr or ""), op, value))
        rules.append(parsed)
    return rules


def test_udev_rules_parse_and_give_each_device_its_name_and_group():
    rules = _rules()
    names = set()
    for rule in rules:
        keys = {k: (op, v) for k, op, v in rule}
        if "SYMLINK" in keys:
            op, name = keys["SYMLINK"]
            assert op == "+="
            names.add(name)
            assert keys["SUBSYSTEM"] == ("==", "tty")
            assert keys["ATTRS{idVendor}"][0] == keys["ATTRS{idProduct}"][0] == "=="
            assert keys["GROUP"] == ("=", "dialout") and keys["MODE"] == ("=", "0660")
            assert keys["ENV{ID_MM_DEVICE_IGNORE}"] == ("=", "1")
    assert names == {"deepxpalm-tactile", "deepxpalm-gripper", "deepxpalm-servos"}
    # The names the example configs and the full-hardware scene open.
    from common.config.typed import load_toml

    assert (
        load_toml(EXAMPLES / "robot.toml")["robot"]["tactile"]["port"] == "/dev/deepxpalm-tactile"
    )
    servos = load_toml(EXAMPLES / "operator.toml")["operator"]["servos"]["port"]
    assert servos == "/dev/deepxpalm-servos"


def test_udev_rules_cover_the_common_usb_serial_bridges():
    text = RULES.read_text()
    for vendor in ("0403", "1a86", "10c4"):  # FTDI, WCH CH340/CH343, Silicon Labs CP210x
        assert f'ATTRS{{idVendor}}=="{vendor}"' in text
    assert "udevadm info" in text
    assert 'ATTR{latency_timer}="1"' in text


@pytest.mark.slow
def test_the_video_unit_starts_a_video_server_the_cli_accepts(tmp_path):
    unit = _parse(_unit("video"))
    assert _get(unit, "Service", "Type") == ["notify"]  # READY=1 once it serves
    assert _get(unit, "Unit", "Before") == ["deepxpalm-robot.service"]
    assert _get(unit, "Service", "User") == ["deepxpalm"]
    assert _get(unit, "Service", "SupplementaryGroups") == ["video"]  # /dev/video*
    assert _get(unit, "Install", "WantedBy") == ["multi-user.target"]
    printed = _config_the_unit_starts(unit, "video", tmp_path)
    assert 'host = "127.0.0.1"' in printed and 'source = "v4l2"' in printed


@pytest.mark.slow
@pytest.mark.pty  # the servo bus's simulator answers through a pseudo-terminal
def test_the_operator_unit_lifts_the_palm_after_any_exit(tmp_path):
    """ExecStopPost= is ``deepxpalm palm lift`` on the example config; run as the unit runs it
    (the servo port pointed at a simulated bus holding a pressed pose), it lifts every linkage."""
    from operator_side.palm.renderer import LinkGlideRenderer, RendererConfig
    from operator_side.servos.calibration import save_calibration
    from operator_side.servos.feetech import FeetechConfig
    from operator_side.servos.sts_sim import FakeStsBus, FakeStsBusConfig

    unit = _parse(_unit("operator"))
    (post,) = _get(unit, "Service", "ExecStopPost")
    argv = shlex.split(post)
    assert argv[0] == INSTALLED and argv[1:3] == ["palm", "lift"]
    assert "/etc/deepxpalm/operator.toml" in argv
    retract = LinkGlideRenderer(RendererConfig(), FeetechConfig().calibration).retract_goals
    with FakeStsBus(FakeStsBusConfig(start_counts=2600, speed_counts_per_s=20000.0)) as bus:
        args = [str(EXAMPLES / "operator.toml") if a.startswith("/etc/") else a for a in argv[1:]]
        calibration = tmp_path / "linkglide-calibration.toml"  # the example's is in /etc
        save_calibration(FeetechConfig().calibration, calibration)
        settings = [
            f'servos.port="{bus.port}"',
            f'servos.calibration_file="{calibration}"',
            "servos.reply_timeout_ms=150.0",  # the simulator answers from a loaded machine
        ]
        overrides = [x for setting in settings for x in ("--set", setting)]
        out = subprocess.run(
            [sys.executable, "-m", "deploy.cli", *args, *overrides],
            capture_output=True,
            text=True,
            timeout=60,
            env=ENV,
        )
        # The torque off is the command's last write, a broadcast nothing answers: the
        # simulator's reader thread (in this process) may not have read it yet.
        released = wait_until(lambda: not any(bus.torque(i) for i in range(1, 7)), 2.0)
        present = [bus.present(i) for i in range(1, 7)]
    assert out.returncode == 0, out.stderr
    assert "palm lifted" in out.stdout
    assert all(abs(p - r) <= 16 for p, r in zip(present, retract, strict=True)), (present, retract)
    assert released, "torque stays on after the lift"


def test_the_router_unit_is_watched_bounded_and_starts_a_router_the_cli_accepts(tmp_path):
    unit = _parse(_unit("router"))
    assert _get(unit, "Service", "Type") == ["notify"]
    assert _get(unit, "Service", "Restart") == ["always"]
    # what the router's access control does not bound, its unit does
    assert _get(unit, "Service", "MemoryMax") == ["256M"]
    printed = _config_the_unit_starts(unit, "router", tmp_path)
    assert "[router]" in printed and 'listen_endpoint = "quic/0.0.0.0:7447"' in printed
