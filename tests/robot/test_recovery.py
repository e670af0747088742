"""A failed device comes back in the background; meanwhile it is refused, not waited for."""

from __future__ import annotations

import threading
import time

import pytest

from common.errors import DeviceError
from robot_side.devices.recovery import DeviceRecovery


class FlakyArm:
    def __init__(self, connect_failures: int = 0) -> None:
        self.connects = 0
        self.connect_failures = connect_failures
        self.broken = False

    def connect(self) -> None:
        self.connects += 1
        if self.connect_failures:
            self.connect_failures -= 1
            raise DeviceError("controller not answering yet")
        self.broken = False

    def disconnect(self) -> None:
        pass

    @property
    def is_connected(self) -> bool:
        return True

    @property
    def needs_reconnect(self) -> bool:
        return self.broken

    def stop(self) -> str:
        if self.broken:
            raise DeviceError("control interface unusable")
        return "stopped"


def test_a_failed_call_is_reraised_refused_meanwhile_and_recovered():
    arm, stop = FlakyArm(connect_failures=1), threading.Event()
    rec = DeviceRecovery(arm, "arm", stop, first_backoff_s=0.05)
    assert rec.call(arm.stop) == "stopped"
    arm.broken = True
    with pytest.raises(DeviceError, match="unusable"):
        rec.call(arm.stop)
    with pytest.raises(DeviceError, match="reconnecting"):
        rec.call(arm.stop)  # refused at once, not queued behind the reconnect
    deadline = time.monotonic() + 3
    while not rec.available and time.monotonic() < deadline:
        time.sleep(0.01)
    assert rec.available and arm.connects == 2 and rec.recoveries == 1
    assert rec.call(arm.stop) == "stopped"


def test_a_refused_call_on_a_live_driver_does_not_reconnect_it():
    class Refusing(FlakyArm):
        def stop(self) -> str:
            raise DeviceError("protective stop")

    arm, stop = Refusing(), threading.Event()
    rec = DeviceRecovery(arm, "arm", stop, first_backoff_s=0.01)
    with pytest.raises(DeviceError, match="protective"):
        rec.call(arm.stop)
    assert rec.available and rec.failures == 0 and arm.connects == 0


def test_stopping_the_node_ends_a_recovery_that_cannot_succeed():
    arm, stop = FlakyArm(connect_failures=10**6), threading.Event()
    rec = DeviceRecovery(arm, "arm", stop, first_backoff_s=0.01, max_backoff_s=0.02)
    arm.broken = True
    with pytest.raises(DeviceError):
        rec.call(arm.stop)
    time.sleep(0.1)
    stop.set()
    rec.join(1.0)
    assert not rec.available and arm.connects > 1


@pytest.mark.slow
def test_a_simulated_arm_recovers_on_the_same_running_simulator():
    """As a real controller stays up while its driver reconnects, the simulator is not restarted.

    Restarting it would put the arm back at home and cost a process start inside the recovery.
    """
    from robot_side.arm.sim import SimulatedArm

    arm, stop = SimulatedArm(), threading.Event()
    arm.connect()
    try:
        sim_before = arm.sim
        host = arm.config.host
        rec = DeviceRecovery(arm, "arm", stop, first_backoff_s=0.05)
        rec.failed()
        deadline = time.monotonic() + 30
        while not rec.available and time.monotonic() < deadline:
            time.sleep(0.02)
        assert rec.available and rec.recoveries == 1
        assert arm.sim is sim_before and arm.sim.running and arm.config.host == host
        assert arm.is_connected and not arm.needs_reconnect
    finally:
        stop.set()
        arm.disconnect()
