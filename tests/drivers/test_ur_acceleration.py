"""How fast a jog gets going, read on the controller's own clock (the UR simulator's stream).

ur-rtde's ``speedL`` takes one acceleration and the controller ramps the turn
at that number in rad/s^2 (URScript ``speedl``: ``aRot`` defaults to ``a``).
Passing the linear limit for every jog turned a wrist at half its configured
angular acceleration, and every correction of a grasp waited on it.
"""

from __future__ import annotations

import itertools
import time

import numpy as np
import pytest

from common.errors import DeviceError
from robot_side.arm.base import ArmLimits
from robot_side.arm.ur_rtde import URArm, URArmConfig

pytestmark = [
    pytest.mark.slow,
    pytest.mark.timeout(60),
    # the heap frozen before the module's arm connects: a full collection holds the GIL the
    # keep-alive's kicks need (quiet_gc_module)
    pytest.mark.usefixtures("quiet_gc_module", "robot_node_priority_module"),
]


@pytest.fixture(scope="module")
def receive(sim):
    import rtde_receive

    r = rtde_receive.RTDEReceiveInterface(sim.host)
    yield r
    r.disconnect()


def _ramp_once(
    arm: URArm, receive, velocity: list[float], part: slice
) -> list[tuple[float, float]]:
    """(controller time, |velocity[part]|) from rest until 95 % of the jog's speed."""
    top = float(np.linalg.norm(velocity[part]))
    samples: list[tuple[float, float]] = []
    deadline = time.monotonic() + 5.0
    last_jog = 0.0
    while time.monotonic() < deadline:
        if time.monotonic() - last_jog > 0.05:  # renewed, as a held key is
            arm.jog(velocity)
            last_jog = time.monotonic()
        speed = float(np.linalg.norm(np.asarray(receive.getActualTCPSpeed())[part]))
        samples.append((receive.getTimestamp(), speed))
        if speed > 0.95 * top:
            break
        time.sleep(0.002)
    arm.stop()
    deadline = time.monotonic() + 3.0  # at rest again, by the controller's own reading
    while np.linalg.norm(receive.getActualTCPSpeed()) > 1e-4:
        assert time.monotonic() < deadline, "the arm did not come to rest after the stop"
        time.sleep(0.01)
    return samples


def _ramp(arm: URArm, receive, velocity: list[float], part: slice) -> float:
    """The slope (per s of controller time) of |velocity[part]| between 20 % and 80 % of it.

    A ramp says nothing about the acceleration, and is taken again (at most three times),
    when it dipped (the jog's own deadman cut it: this test's renewals starved past
    ``jog_timeout_s`` on a busy machine) or has too few samples on its slope (the
    simulator's stream stood still: its process starved; or the controller's watchdog
    stopped a driver whose deadman this process starved, and the arm is connected again).
    """
    top = float(np.linalg.norm(velocity[part]))
    samples: list[tuple[float, float]] = []
    for _ in range(3):
        if arm.needs_reconnect:
            arm.disconnect()
            arm.connect()
        try:
            samples = _ramp_once(arm, receive, velocity, part)
        except DeviceError:  # the program stopped under the jog (above): reconnect and again
            if not arm.needs_reconnect:
                raise
            continue
        speeds = [v for _, v in samples]
        ramp = [(t, v) for t, v in samples if 0.2 * top <= v <= 0.8 * top]
        steady = all(b >= a - 0.02 * top for a, b in itertools.pairwise(speeds))
        if steady and len({t for t, _ in ramp}) >= 5:
            break
    else:
        raise AssertionError(f"no ramp could be read (dipped, or too few samples): {samples}")
    t, v = np.array(ramp).T
    return float(np.polyfit(t, v, 1)[0])


def test_a_wrist_turn_ramps_at_the_angular_limit_and_a_translation_at_the_linear(sim, receive):
    limits = ArmLimits()  # the defaults a lab runs with: 0.5 m/s^2, 1.0 rad/s^2
    assert limits.angular_acceleration_rad_s2 > limits.linear_acceleration_m_s2
    arm = URArm(URArmConfig(host=sim.host, limits=limits, stale_after_s=0.5))
    arm.connect()
    try:
        w = limits.max_angular_speed_rad_s
        turn = _ramp(arm, receive, [0, 0, 0, 0, w, 0], slice(3, 6))
        assert turn == pytest.approx(limits.angular_acceleration_rad_s2, rel=0.1)
        v = limits.max_linear_speed_m_s
        # a jog that translates and turns: neither part beyond its own limit
        # (the controller ramps the translation at a and the turn at aRot, each on its own)
        shift = _ramp(arm, receive, [v, 0, 0, 0, 0.1, 0], slice(0, 3))
        assert shift == pytest.approx(limits.linear_acceleration_m_s2, rel=0.1)
    finally:
        arm.disconnect()
