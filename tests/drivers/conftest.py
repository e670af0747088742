"""What the UR driver's test files share: a simulated controller per file."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="module")
def sim():
    """A UR simulator in a process of its own (ur-rtde's constructors hold the GIL)."""
    from robot_side.arm.sim import URSimProcess

    s = URSimProcess().start()
    yield s
    s.stop()
