"""deepxpalm doctor passes on the demo scene and names a missing port, a wrong key, a dead peer."""

from __future__ import annotations

import dataclasses
import json
import os
import socket
import subprocess

import pytest
from deploy_support import ENV, cli, loopback
from tests_support import free_ports

from common.devices.preflight import Finding, PreflightContext
from deploy.doctor import FAIL, PASS, SKIP, WARN, DoctorOptions, diagnose, node_section
from deploy.keys_cli import generate
from deploy.scene import load_scene_dict
from robot_side.gripper.memory import MemoryGripper

#: No test may depend on whether this machine has the units' user.
#: the real-time probe is tests/deploy/test_doctor_realtime.py's: a short one here (it still runs)
OPTS = DoctorOptions(
    peer_timeout_s=1.5,
    device_timeout_s=15.0,
    service_user="nobody-deepxpalm",
    keep_alive_probe_s=0.1,
)
NO_PEER = dataclasses.replace(OPTS, check_peer=False)


def _link(tel: int, cmd: int, security: dict | None = None) -> dict:
    return {
        "telemetry_endpoint": loopback(tel),
        "command_endpoint": loopback(cmd),
        "security": security or {},
    }


def _light_robot(tel: int, cmd: int, **extra) -> dict:
    """A robot table with in-process devices only: the doctor's own logic under test."""
    return {
        "render": {"mode": "mask_ground_truth"},
        "tactile": {"kind": "scripted"},
        "link": _link(tel, cmd, extra.pop("security", None)),
        **extra,
    }


def _curve_robot(keys) -> dict:
    return {
        "mode": "curve",
        "secret_key_file": str(keys.robot_secret),
        "authorized_keys_dir": str(keys.authorized),
    }


def _curve_operator(keys, server_key=None, secret=None) -> dict:
    return {
        "mode": "curve",
        "secret_key_file": str(secret or keys.operator_secret),
        "server_public_key_file": str(server_key or keys.robot_public),
    }


def _statuses(report) -> dict[str, str]:
    return {c.name: c.status for c in report.checks}


# ------------------------------------------------------------------ demo scene
@pytest.mark.slow
def test_demo_scene_passes_for_the_robot_through_the_cli():
    """The whole command on the shipped demo scene: its wire-level simulators answer (the
    link's ports left to the robot: 0, whatever is free when it binds)."""
    out = subprocess.run(
        cli(
            "doctor",
            "--scene",
            "demo",
            "--role",
            "robot",
            "--set",
            f'robot.link.telemetry_endpoint="{loopback(0)}"',
            "--set",
            f'robot.link.command_endpoint="{loopback(0)}"',
            "--peer-timeout",
            "0.5",
            "--device-timeout",
            "40",  # the UR simulator is a child process: slow to start on a loaded machine
            "--json",
        ),
        capture_output=True,
        text=True,
        timeout=120,
        env=ENV,
    )
    assert out.returncode == 0, out.stdout + out.stderr
    report = json.loads(out.stdout)
    status = {c["name"]: c["status"] for c in report["checks"]}
    assert report["ok"] and report["role"] == "robot"
    for name in ("config", "classifier", "robot ports", "device robot.tactile"):
        assert status[name] == PASS, report
    assert status["device robot.gripper"] == status["device robot.arm"] == PASS
    assert status["peer operator"] == WARN  # nobody runs the operator: not a failure


def test_demo_scene_passes_for_the_operator_with_the_robot_running(robot_in_thread):
    tel, cmd = free_ports(2)
    robot_in_thread(tel, cmd)
    data = node_section(
        load_scene_dict(
            "demo",
            [
                f'operator.link.telemetry_endpoint="{loopback(tel)}"',
                f'operator.link.command_endpoint="{loopback(cmd)}"',
                # The demo's fake STS bus answers the SDK within its fixed 34 ms wall-clock
                # timeout only on a quiet machine; the servo driver has its own tests.
                'operator.servos={kind="in_memory"}',
            ],
        ),
        "operator",
    )
    report = diagnose("operator", data, "demo", OPTS)
    assert report.ok, report.to_text()
    assert report.find("device operator.servos").status == PASS
    assert report.find("peer robot").status == PASS
    clock = report.find("clock")
    assert clock.status == PASS and "round trip" in clock.detail


def test_robot_measures_the_clock_to_a_running_operator(operator_in_thread, keys):
    tel, cmd = free_ports(2)
    operator_in_thread(tel, cmd, security=_curve_operator(keys))
    report = diagnose("robot", _light_robot(tel, cmd, security=_curve_robot(keys)), "t", OPTS)
    assert report.ok, report.to_text()
    assert report.find("link security").status == PASS
    assert report.find("keys: robot secret").status == PASS
    assert report.find("keys: operator allowlist").status == PASS
    assert report.find("peer operator").status == PASS
    assert report.find("clock").status == PASS


# ------------------------------------------------------------- missing port
def test_missing_serial_port_fails_and_says_how_to_name_it(tmp_path):
    tel, cmd = free_ports(2)
    port = str(tmp_path / "deepxpalm-tactile")
    data = _light_robot(tel, cmd)
    data["tactile"] = {"kind": "serial", "port": port}
    report = diagnose("robot", data, "t", NO_PEER)
    check = report.find("device robot.tactile")
    assert check.status == FAIL
    assert check.detail == f"serial port {port} does not exist"
    assert "/dev/serial/by-id" in check.fix and "99-deepxpalm.rules" in check.fix
    assert not report.ok


def test_a_stale_udev_link_is_called_one(tmp_path):
    link = tmp_path / "deepxpalm-servos"
    link.symlink_to(tmp_path / "ttyUSB7")
    data = {"servos": {"kind": "feetech", "port": str(link)}}
    report = diagnose("operator", data, "t", NO_PEER)
    check = report.find("device operator.servos")
    assert check.status == FAIL
    assert "does not exist (the udev link is there but its device is gone)" in check.detail


@pytest.mark.slow
def test_serial_board_answers_at_its_baud_and_not_at_another():
    """The real driver against the pty board simulator, through the doctor."""
    from robot_side.tactile.board_sim import TactileBoardSimulator

    tel, cmd = free_ports(2)
    with TactileBoardSimulator() as board:
        data = _light_robot(tel, cmd)
        data["tactile"] = {"kind": "serial", "port": board.port, "baudrate": 921600}
        good = diagnose("robot", data, "t", NO_PEER).find("device robot.tactile")
        data["tactile"]["baudrate"] = 115200
        wrong = diagnose("robot", data, "t", NO_PEER).find("device robot.tactile")
    assert good.status == PASS and "answers" in good.detail
    assert wrong.status == FAIL and "baud" in wrong.detail.lower()


def test_unreachable_network_device_fails_before_its_driver_runs():
    (port,) = free_ports(1)
    tel, cmd = free_ports(2)
    data = _light_robot(tel, cmd)
    data["gripper"] = {"kind": "robotiq_socket", "host": "127.0.0.1", "port": port}
    check = diagnose("robot", data, "t", NO_PEER).find("device robot.gripper")
    assert check.status == FAIL
    assert f"127.0.0.1:{port} refused the connection" in check.detail
    assert "URCap" in check.fix


# ------------------------------------------------------------------ wrong keys
@pytest.mark.slow
def test_wrong_robot_key_on_the_operator_fails_the_handshake(keys, robot_in_thread, tmp_path):
    tel, cmd = free_ports(2)
    robot_in_thread(tel, cmd, security=_curve_robot(keys))
    stranger, _ = generate(tmp_path / "other", "robot")
    data = {"link": _link(tel, cmd, _curve_operator(keys, server_key=stranger))}
    report = diagnose("operator", data, "t", OPTS)
    check = report.find("peer robot")
    assert check.status == FAIL, report.to_text()
    assert "CURVE handshake with the robot failed" in check.detail
    assert f"{stranger} is not the key the robot holds" in check.detail
    assert "keys show" in check.fix
    # The right key passes, same robot, same ports.
    data = {"link": _link(tel, cmd, _curve_operator(keys))}
    assert diagnose("operator", data, "t", OPTS).find("peer robot").status == PASS


@pytest.mark.slow
def test_operator_key_not_on_the_robots_allowlist_is_refused(keys, robot_in_thread, tmp_path):
    tel, cmd = free_ports(2)
    robot_in_thread(tel, cmd, security=_curve_robot(keys))
    _, unlisted = generate(tmp_path / "other", "operator-bob")
    data = {"link": _link(tel, cmd, _curve_operator(keys, secret=unlisted))}
    check = diagnose("operator", data, "t", OPTS).find("peer robot")
    assert check.status == FAIL
    assert "the robot refused this operator's key" in check.detail
    assert "deepxpalm keys allow" in check.fix


@pytest.mark.slow
def test_robot_names_the_operator_key_it_refused(keys, operator_in_thread, tmp_path):
    tel, cmd = free_ports(2)
    bob_public, bob_secret = generate(tmp_path / "other", "operator-bob")
    operator_in_thread(tel, cmd, security=_curve_operator(keys, secret=bob_secret))
    report = diagnose("robot", _light_robot(tel, cmd, security=_curve_robot(keys)), "t", OPTS)
    check = report.find("peer operator")
    assert check.status == FAIL
    import zmq.auth

    bob_z85 = zmq.auth.load_certificate(bob_public)[0].decode()
    assert bob_z85 in check.detail


def test_secret_key_readable_by_others_fails_with_chmod(keys, tmp_path):
    os.chmod(keys.operator_secret, 0o644)
    tel, cmd = free_ports(2)
    report = diagnose("operator", {"link": _link(tel, cmd, _curve_operator(keys))}, "t", OPTS)
    check = report.find("keys: operator secret")
    assert check.status == FAIL
    assert "is open to other users" in check.detail and "-rw-r--r--" in check.detail
    assert check.fix == f"chmod 600 {keys.operator_secret}"
    assert report.find("peer robot").status == SKIP


def test_public_key_given_as_the_secret_and_own_key_as_the_robots(keys):
    tel, cmd = free_ports(2)
    security = _curve_operator(keys, secret=keys.operator_public)
    check = diagnose("operator", {"link": _link(tel, cmd, security)}, "t", OPTS).find("keys")
    assert check.status == FAIL and "holds only a public key" in check.detail
    security = _curve_operator(keys, server_key=keys.operator_public)
    check = diagnose("operator", {"link": _link(tel, cmd, security)}, "t", OPTS).find(
        "keys: robot public"
    )
    assert check.status == FAIL and "this operator's own public key" in check.detail


def test_empty_allowlist_fails_on_the_robot(keys):
    for key in keys.authorized.glob("*.key"):
        key.unlink()
    tel, cmd = free_ports(2)
    report = diagnose("robot", _light_robot(tel, cmd, security=_curve_robot(keys)), "t", NO_PEER)
    check = report.find("keys: operator allowlist")
    assert check.status == FAIL and "holds no operator key" in check.detail


def test_plain_tcp_off_loopback_is_a_failure():
    data = {"link": {"telemetry_endpoint": "tcp://10.20.0.15:5555"}}
    check = diagnose("operator", data, "t", NO_PEER).find("link security")
    assert check.status == FAIL and "curve" in check.fix


# ----------------------------------------------------------- unreachable peer
def test_robot_not_running_fails_with_what_to_start():
    tel, cmd = free_ports(2)
    report = diagnose("operator", {"link": _link(tel, cmd)}, "t", OPTS)
    check = report.find("peer robot")
    assert check.status == FAIL
    assert check.detail == (
        f"robot unreachable at {loopback(tel)}: 127.0.0.1:{tel} refused the connection "
        "(the host is up; nothing listens there)"
    )
    assert "deepxpalm-robot" in check.fix
    assert not report.ok


def test_a_stranger_on_the_robots_port_is_named():
    tel, cmd = free_ports(2)
    squatter = socket.socket()
    squatter.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    squatter.bind(("127.0.0.1", tel))
    squatter.listen()
    try:
        report = diagnose("robot", _light_robot(tel, cmd), "t", OPTS)
    finally:
        squatter.close()
    check = report.find("robot ports")
    assert check.status == FAIL and "another process holds the port" in check.detail
    assert "ss -ltnp" in check.fix


# ------------------------------------------------------------------- the CLI
@pytest.mark.slow
def test_cli_exits_1_with_a_json_list_of_failures(tmp_path):
    config = tmp_path / "operator.toml"
    config.write_text(
        '[operator.servos]\nkind = "feetech"\nport = "/dev/deepxpalm-servos-missing"\n'
    )
    out = subprocess.run(
        cli("doctor", "--config", str(config), "--json", "--no-peer", "--keep-alive-probe", "0.1"),
        capture_output=True,
        text=True,
        timeout=60,
        env=ENV,
    )
    assert out.returncode == 1, out.stdout + out.stderr
    report = json.loads(out.stdout)
    assert report["role"] == "operator" and not report["ok"]  # the role came from the file
    failed = [c for c in report["checks"] if c["status"] == FAIL]
    assert [c["name"] for c in failed] == ["device operator.servos"]
    assert failed[0]["fix"]


@pytest.mark.slow
def test_cli_text_report_shows_the_fix_under_each_failure(tmp_path):
    config = tmp_path / "robot.toml"
    config.write_text('[robot.render]\nmode = "sideways"\n')
    out = subprocess.run(
        cli("doctor", "--config", str(config), "--keep-alive-probe", "0"),
        capture_output=True,
        text=True,
        timeout=60,
        env=ENV,
    )
    assert out.returncode == 1
    lines = out.stdout.splitlines()
    i = next(i for i, line in enumerate(lines) if line.strip().startswith("FAIL"))
    assert "robot.render.mode" in lines[i] and "fix:" in lines[i + 1]
    assert "NOT ready" in out.stdout


@pytest.mark.slow
@pytest.mark.parametrize("role", ["robot", "operator"])
def test_a_scene_for_both_machines_needs_a_role(role):
    out = subprocess.run(
        cli(
            "doctor",
            "--scene",
            "covid_lab",
            "--no-peer",
            "--no-connect",
            "--json",
            "--keep-alive-probe",
            "0",
        ),
        capture_output=True,
        text=True,
        timeout=60,
        env=ENV,
    )
    assert out.returncode == 1
    assert "--role" in json.loads(out.stdout)["checks"][0]["detail"]


def test_missing_robot_public_key_says_where_to_copy_it_from(keys, tmp_path):
    tel, cmd = free_ports(2)
    missing = tmp_path / "robot.key"
    security = _curve_operator(keys, server_key=missing)
    check = diagnose("operator", {"link": _link(tel, cmd, security)}, "t", NO_PEER).find(
        "keys: robot public"
    )
    assert check.status == FAIL and check.detail == f"{missing} does not exist"
    assert "robot PC" in check.fix


# ------------------------------------------------------------- device kinds
class _OwnKindGripper(MemoryGripper):
    """A kind doctor has never heard of: what it reports comes from the device alone."""

    simulated = False

    def _preflight(self, context: PreflightContext) -> list[Finding]:
        return [Finding(WARN, "the gripper's LED blinks red", f"press reset ({context.where})")]


def test_doctor_reports_a_kinds_own_preflight_findings(monkeypatch):
    import robot_side.gripper

    monkeypatch.setitem(robot_side.gripper.KINDS, "own_kind", f"{__name__}:_OwnKindGripper")
    tel, cmd = free_ports(2)
    data = _light_robot(tel, cmd, gripper={"kind": "own_kind"})
    check = diagnose("robot", data, "t", NO_PEER).find("device robot.gripper")
    assert (check.status, check.detail) == (WARN, "the gripper's LED blinks red")
    assert check.fix == "press reset (robot.gripper)"


# ----------------------------------------------------------------- video
@pytest.mark.slow
def test_the_robots_video_server_is_checked_where_viewers_will_reach_it():
    pytest.importorskip("aiortc")
    from robot_side.camera.config import TestPatternConfig
    from robot_side.camera.test_pattern import TestPatternCamera
    from robot_side.video.server import VideoConfig, VideoServer

    tel, cmd, dead = free_ports(3)
    robot = _light_robot(tel, cmd)
    robot["link"]["video_url"] = f"ws://127.0.0.1:{dead}/"
    check = diagnose("robot", robot, "t", NO_PEER).find("video server")
    assert check.status == FAIL and f"127.0.0.1:{dead}" in check.detail
    assert "deepxpalm video" in check.fix
    source = TestPatternCamera(TestPatternConfig(width=320, height=240))
    with VideoServer(source, VideoConfig(port=0)) as server:
        robot["link"]["video_url"] = server.base_url  # no token: refused, and said so
        check = diagnose("robot", robot, "t", NO_PEER).find("video server")
        assert check.status == FAIL and "token" in check.detail and "video_token_file" in check.fix
        robot["link"]["video_url"] = server.url
        check = diagnose("robot", robot, "t", NO_PEER).find("video server")
        assert check.status == PASS and server.token not in check.detail
        assert server.viewing.frames_encoded == 0  # a knock on the door, no viewer: nothing encoded
