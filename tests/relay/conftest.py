"""Fixtures of the relay tests."""

from __future__ import annotations

import pytest


@pytest.fixture
def arm_sim():
    from robot_side.arm.sim import URSimProcess

    sim = URSimProcess().start()
    yield sim
    sim.stop()
