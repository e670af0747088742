"""`deepxpalm doctor` shows the peer's own view of its links, read from its heartbeat."""

from __future__ import annotations

from common.devices.preflight import PASS, WARN
from deploy.doctor.link import link_health_verdict
from deploy.doctor.report import Report


def test_a_link_the_robot_reports_down_is_a_warning_with_what_to_check() -> None:
    report = Report("operator", "test")
    stats = {"link_telemetry_up": 0.0, "link_telemetry_reopened": 2.0, "link_commands_up": 1.0}
    link_health_verdict(report, "robot", stats)
    check = report.find("robot links")
    assert check.status == WARN
    assert "telemetry link down" in check.detail and "opened again 2x" in check.detail
    assert "--role router" in check.fix


def test_links_up_pass_and_name_their_reopens() -> None:
    report = Report("robot", "test")
    link_health_verdict(
        report,
        "operator",
        {"link_telemetry_up": 1.0, "link_commands_up": 1.0, "link_commands_reopened": 1.0},
    )
    check = report.find("operator links")
    assert check.status == PASS
    assert check.detail.endswith("telemetry up, commands up (opened again 1x)")


def test_a_direct_link_says_nothing() -> None:
    report = Report("operator", "test")
    link_health_verdict(report, "robot", {"frames": 3.0})
    assert report.checks == []


def test_a_fabric_node_without_its_router_is_a_warning() -> None:
    report = Report("operator", "test")
    link_health_verdict(report, "robot", {"link_fabric_router_up": 0.0})
    check = report.find("robot links")
    assert check.status == WARN and "fabric_router link down" in check.detail
