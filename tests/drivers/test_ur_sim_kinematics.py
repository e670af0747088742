"""The UR simulator's joints follow its TCP without speed spikes, whatever the tick lengths.

A loaded machine steps the simulated controller by the real time that passed:
long ticks, then short ones. The joint speeds it reports (and the lab world's
safety check reads) must stay those of the motion, never a catch-up artefact.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robot_side.arm.sim.kinematics import HOME_Q, KinematicArm, forward

pytestmark = pytest.mark.slow

TICK = 0.002


def _jog(arm: KinematicArm) -> None:
    arm.speed_l(np.array([0.1, -0.05, 0.08, 0.0, 0.0, 0.3]), 1.0)


#: how long the jogs below run: the TCP moves 0.14 m a second, and farther on the joints'
#: speeds for the same TCP speed grow (4 s of it reached 12 rad/s, near a singularity)
JOG_S = 0.6


@functools.cache
def _qd_limit() -> float:
    """Half as much again as the fastest joint of the same jog on a steady 500 Hz tick."""
    arm = KinematicArm()
    _jog(arm)
    top = 0.0
    for _ in range(round(JOG_S / TICK)):
        arm.step(TICK)
        top = max(top, float(np.max(np.abs(arm.qd))))
    return 1.5 * top + 1e-3


@settings(max_examples=30, deadline=None)
@given(st.lists(st.sampled_from([0.05, 0.02, 0.002, 1e-4, 1e-5]), min_size=20, max_size=80))
def test_irregular_ticks_never_spike_the_joint_speeds(ticks):
    limit = _qd_limit()
    arm = KinematicArm()
    _jog(arm)
    elapsed = 0.0
    for dt in ticks:
        if elapsed + dt > JOG_S:  # as far as the steady jog the limit comes from
            break
        elapsed += dt
        arm.step(dt)
        assert np.all(np.isfinite(arm.qd))
        assert float(np.max(np.abs(arm.qd))) <= limit, (dt, arm.qd)
    # and the joints put the TCP where the simulator says it is
    t, _ = forward(arm.q, arm.tcp)
    assert np.linalg.norm(t[:3, 3] - arm.pos) < 1e-6


def test_a_stop_after_a_long_tick_decelerates_without_a_spike():
    limit = _qd_limit()
    arm = KinematicArm()
    _jog(arm)
    for _ in range(100):
        arm.step(TICK)
    arm.step(0.05)  # the machine stalled
    arm.stop(10.0)
    for dt in (1e-4, 1e-4, 0.002, 0.05, 1e-4, 0.002):
        arm.step(dt)
        assert float(np.max(np.abs(arm.qd))) <= limit, (dt, arm.qd)
    assert not np.allclose(arm.q, HOME_Q)
