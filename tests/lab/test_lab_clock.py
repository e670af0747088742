"""The world's clock report: sim/wall per window, the slowest since a trial began."""

from __future__ import annotations

import pytest

from robot_side.lab.clock import SimWallMeter, sim_wall_between


def test_the_meter_reports_each_closed_window_and_the_slowest_since_the_trial_began():
    meter = SimWallMeter(window_s=1.0)
    assert meter.update(0.0, 0.0) is None and meter.last is None
    assert meter.update(0.5, 0.5) is None, "a window closes after a full second of wall time"
    assert meter.update(1.0, 1.0) == pytest.approx(1.0)
    assert meter.update(2.0, 1.6) == pytest.approx(0.6), "a world that stepped 0.6 s in 1 s"
    assert (meter.lowest, meter.windows_behind) == (pytest.approx(0.6), 1)
    meter.mark()
    assert meter.update(3.0, 2.59) == pytest.approx(0.99)
    assert (meter.last, meter.lowest, meter.windows_behind) == (
        pytest.approx(0.99),
        pytest.approx(0.99),
        0,
    ), "a new trial counts its own windows"


def test_sim_wall_between_two_stats():
    before = {"sim_time_s": 10.0, "wall_time_s": 10.5}
    assert sim_wall_between(before, {"sim_time_s": 12.0, "wall_time_s": 14.5}) == 0.5
    assert sim_wall_between(before, before) is None
