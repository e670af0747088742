"""deepxpalm doctor on the relay host, and from a robot whose link goes through a relay."""

from __future__ import annotations

import tomllib

from common.preflight import FAIL, PASS, WARN
from deploy.doctor.cli import diagnose
from deploy.doctor.report import DoctorOptions
from harness.fleet import Fleet
from relay_side.config import RelayConfig, RelaySecurityConfig
from relay_side.relay import Relay

OPTIONS = DoctorOptions(check_peer=True, connect_devices=False, service_user="nobody-here")


def _fleet(tmp_path) -> Fleet:
    return Fleet(robots=["cell1"], operators={"alice": "controller"}, workdir=tmp_path)


def _relay_table(fleet: Fleet) -> dict:
    return {
        "robots_telemetry_endpoint": fleet.robots_telemetry,
        "robots_command_endpoint": fleet.robots_command,
        "operators_telemetry_endpoint": fleet.ops_telemetry,
        "operators_command_endpoint": fleet.ops_command,
        "roster_file": str(fleet.roster),
        "security": {"mode": "curve", "secret_key_file": str(fleet.members["relay"].curve_secret)},
    }


def test_a_ready_relay_host_passes_and_a_running_relay_is_recognised(tmp_path):
    fleet = _fleet(tmp_path)
    table = _relay_table(fleet)
    report = diagnose("relay", table, "relay.toml", OPTIONS)
    assert report.find("config").status == PASS
    assert report.find("roster").status == PASS
    assert report.find("keys: relay").status == PASS
    assert all(c.status == PASS for c in report.checks if c.name.startswith("port "))
    config = RelayConfig(
        **{k: v for k, v in table.items() if k not in ("security", "roster_file")},
        roster_file=fleet.roster,
        security=RelaySecurityConfig(
            mode="curve", secret_key_file=fleet.members["relay"].curve_secret
        ),
    )
    with Relay(config):
        busy = diagnose("relay", table, "relay.toml", OPTIONS)
    ports = [c for c in busy.checks if c.name.startswith("port ")]
    assert len(ports) == 4 and all(c.status == WARN for c in ports), ports


def test_a_bad_roster_or_a_readable_key_fails(tmp_path):
    fleet = _fleet(tmp_path)
    table = _relay_table(fleet)
    bad = tmp_path / "bad.toml"
    bad.write_text('[[operator]]\nname = "x"\nrole = "boss"\n')
    table["roster_file"] = str(bad)
    fleet.members["relay"].curve_secret.chmod(0o644)
    report = diagnose("relay", table, "relay.toml", OPTIONS)
    assert report.find("roster").status == FAIL and "boss" in report.find("roster").detail
    assert report.find("keys: relay").status == FAIL


def test_a_robot_in_relay_mode_is_told_whether_the_relay_answers(tmp_path):
    fleet = _fleet(tmp_path)
    toml = fleet.robot_config("cell1", None)
    robot = tomllib.loads(toml.read_text())["robot"]
    report = diagnose("robot", robot, str(toml), OPTIONS)
    assert report.find("robot name").status == PASS
    assert report.find("roster").status == PASS
    relay_checks = [c for c in report.checks if c.name.startswith("relay ")]
    assert len(relay_checks) == 2 and all(c.status == FAIL for c in relay_checks)
    table = _relay_table(fleet)
    config = RelayConfig(
        **{k: v for k, v in table.items() if k not in ("security", "roster_file")},
        roster_file=fleet.roster,
        security=RelaySecurityConfig(
            mode="curve", secret_key_file=fleet.members["relay"].curve_secret
        ),
    )
    with Relay(config):
        up = diagnose("robot", robot, str(toml), OPTIONS)
    relay_checks = [c for c in up.checks if c.name.startswith("relay ")]
    assert len(relay_checks) == 2 and all(c.status == PASS for c in relay_checks)


def test_the_doctor_says_whether_the_robots_stream_is_signed_and_checked(tmp_path):
    fleet = _fleet(tmp_path)  # the fleet's robots sign, its operators check
    toml = fleet.robot_config("cell1", None)
    robot = tomllib.loads(toml.read_text())["robot"]
    signed = diagnose("robot", robot, str(toml), OPTIONS).find("signed stream")
    assert signed.status == PASS and fleet.signing_key("cell1").hex() in signed.detail
    del robot["link"]["signing_key_file"]
    unsigned = diagnose("robot", robot, str(toml), OPTIONS).find("signed stream")
    assert unsigned.status == FAIL and "will not start" in unsigned.detail
    robot["link"]["unsigned_stream"] = True
    opted_out = diagnose("robot", robot, str(toml), OPTIONS).find("signed stream")
    assert opted_out.status == WARN and "forge" in opted_out.detail
    operator = {
        "link": {
            "robot_name": "cell1",
            "telemetry_endpoint": fleet.ops_telemetry,
            "command_endpoint": fleet.ops_command,
            "robot_key_file": str(tmp_path / "missing.sign"),
            "security": fleet.client_security("alice"),
        }
    }
    wrong = diagnose("operator", operator, "operator.toml", OPTIONS).find("signed stream")
    assert wrong.status == FAIL and "missing.sign" in wrong.detail


def test_the_doctor_says_which_roster_the_relay_holds_and_why_it_refused_a_file(tmp_path):
    fleet = _fleet(tmp_path)
    table = _relay_table(fleet)
    table["roster_status_file"] = str(tmp_path / "relay-roster.json")
    listed = diagnose("relay", table, "relay.toml", OPTIONS).find("roster")
    assert "1 robots (cell1), 1 controllers (alice), 0 observers" in listed.detail
    config = RelayConfig(
        **{k: v for k, v in table.items() if k not in ("security", "roster_file")},
        roster_file=fleet.roster,
        security=RelaySecurityConfig(
            mode="curve", secret_key_file=fleet.members["relay"].curve_secret
        ),
    )
    with Relay(config) as relay:
        held = diagnose("relay", table, "relay.toml", OPTIONS).find("roster in force")
        assert held.status == PASS and "1 robots (cell1)" in held.detail, held
        good = fleet.roster.read_text()
        fleet.roster.write_text(good[: good.index("[[robot]]")])  # cut: no robot left
        assert not relay.reload_roster()
        refused = diagnose("relay", table, "relay.toml", OPTIONS).find("roster in force")
        assert refused.status == WARN, refused
        assert "would remove every robot" in refused.detail and "(cell1)" in refused.detail
