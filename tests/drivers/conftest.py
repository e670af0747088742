"""What the driver test files share: a simulated controller per file, the simulators' priority."""

from __future__ import annotations

import contextlib
import os
import threading

import pytest

from common.devices.lifecycle import SIMULATED_HARDWARE_NICE


@pytest.fixture(scope="module")
def sim():
    """A UR simulator in a process of its own (ur-rtde's constructors hold the GIL)."""
    from robot_side.arm.sim import URSimProcess

    s = URSimProcess().start()
    yield s
    s.stop()


@pytest.fixture(autouse=True)
def at_the_simulators_priority():
    """The test's thread at the simulated hardware's priority, then back.

    A driver and a simulator served from the same process share its GIL. With the
    test's thread (the driver's caller) below the simulator's thread, the test's thread
    was preempted by other work while it held the GIL, and the simulator, at the higher
    priority, could not answer: six servos silent through 34 ms windows, replies 120 ms
    late, on a quiet machine with four test workers (a priority inversion). The operator
    node runs its simulated servos the same way, at one priority (its unit's -10).
    """
    tid = threading.get_native_id()
    before = os.getpriority(os.PRIO_PROCESS, tid)
    with contextlib.suppress(OSError):
        os.setpriority(os.PRIO_PROCESS, tid, min(before, SIMULATED_HARDWARE_NICE))
    yield
    with contextlib.suppress(OSError):
        os.setpriority(os.PRIO_PROCESS, tid, before)
