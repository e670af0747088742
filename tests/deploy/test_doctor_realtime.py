"""`deepxpalm doctor` says whether the arm's keep-alive runs real-time here, and how on time."""

from __future__ import annotations

import os

from tests_support import fifo_granted

from common.devices.preflight import WARN
from deploy.doctor.report import Report
from deploy.doctor.system import check_realtime


def test_the_robot_is_told_what_its_keep_alive_gets_and_its_measured_period():
    report = Report("robot", "test")
    check_realtime(report, None, "robot")
    check = report.find("real-time scheduling")
    assert "woke with period p99" in check.detail and "max" in check.detail
    if fifo_granted():
        assert "SCHED_FIFO priority 20" in check.detail
    else:
        assert check.status == WARN and "LimitRTPRIO" in check.fix


def test_where_fifo_is_refused_the_keep_alive_runs_at_a_niceness_and_that_is_a_warning(
    monkeypatch,
):
    def refuse(*args):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    report = Report("robot", "test")
    check_realtime(report, None, "robot")
    check = report.find("real-time scheduling")
    assert check.status == WARN
    assert "SCHED_FIFO refused: Operation not permitted" in check.detail
    assert "controller stops the arm" in check.detail and "LimitRTPRIO=20" in check.fix


def test_the_operator_has_no_keep_alive_to_probe():
    report = Report("operator", "test")
    check_realtime(report, None, "operator")
    assert report.checks == []
