"""The scripted operator: how it reads the palm, and that its corrections converge.

The policy runs against a truthful palm (the ideal mask of the true pattern)
and an arm that moves exactly as jogged, so what is tested is the operator's
reasoning, not perception or the link (the task benchmark measures those on
the lab world, `deepxpalm bench --only task`).
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from common.rotation import matrix_to_rotvec, rotvec_to_matrix
from common.tactile.contract import MASKS, N_PATTERNS, pattern_of
from harness.scripted_operator import (
    POSE_KEYS,
    TARGET_PATTERN,
    ScriptedOperator,
    ScriptedOperatorConfig,
    lean_and_side,
    read_palm,
    says_lift,
)

#: the UR simulator's home TCP pose: tool z down, fingers closing along base x
HOME = np.array([-0.2985, -0.131, 0.1532, 0.0, math.pi, 0.0])
#: the pads' centre sits this far down the pipette (m): a lean moves the band sideways
DEPTH_M = 0.020
SIDE_MM = 3.0  # a band this far off the centre is "left" or "right" (the lab's rule)


class PalmAndArm:
    """An arm that moves exactly as jogged and a palm that presses the true pattern's mask."""

    def __init__(self, tilt_deg: float, offset_mm: float, dt: float) -> None:
        self.tilt_deg, self.offset_mm, self.dt = tilt_deg, offset_mm, dt
        self.pose = HOME.copy()
        self.closed = False
        self.commands: list[str] = []

    def send_command(self, action, grip_level=None, velocity=None):
        self.commands.append(action)
        if action == "arm_jog":
            v = np.asarray(velocity, dtype=float)
            assert np.all(np.isfinite(v)), "the operator never sends a non-finite jog"
            self.pose[:3] += v[:3] * self.dt
            turn = rotvec_to_matrix(v[3:] * self.dt)
            self.pose[3:] = matrix_to_rotvec(turn @ rotvec_to_matrix(self.pose[3:]))
        elif action == "gripper_close":
            self.closed = True
        elif action == "gripper_open":
            self.closed = False

    def true_pattern(self) -> int:
        r_home = rotvec_to_matrix(HOME[3:])
        r = rotvec_to_matrix(self.pose[3:])
        rel = r_home.T @ r  # the wrist's turn about the start tool's y
        turn_deg = math.degrees(math.atan2(rel[0, 2], rel[0, 0]))
        shift_mm = float(r_home[:, 0] @ (self.pose[:3] - HOME[:3])) * 1000
        theta = (90.0 + self.tilt_deg + turn_deg) % 180.0
        angle = round(theta / 45.0) % 4
        band_mm = self.offset_mm + DEPTH_M * 1000 * math.tan(math.radians(self.tilt_deg))
        band_mm -= shift_mm
        position = 0 if abs(band_mm) <= SIDE_MM else (2 if band_mm > 0 else 1)
        return pattern_of(angle, position)

    def snapshot(self):
        stim = MASKS[self.true_pattern()] * 2.0 if self.closed else np.zeros((3, 3))
        return SimpleNamespace(
            link_state="ok",
            robot_stats=dict(zip(POSE_KEYS, self.pose.tolist(), strict=True)),
            stimulus=stim,
            pattern=None,
        )


def fast_config() -> ScriptedOperatorConfig:
    """The default policy with every wait shortened: the fake arm moves per jog, not per second."""
    return ScriptedOperatorConfig(
        jog_period_s=0.0005,
        close_wait_s=0.0,
        settle_s=0.001,
        release_s=0.0,
        feel_timeout_s=0.2,
        blind_close_s=0.0,
        move_timeout_s=20.0,
        gain_per_s=40.0,
        speed_m_s=0.5,
        turn_speed_rad_s=5.0,
    )


def run_trial(tilt_deg: float, offset_mm: float, feedback: bool = True):
    config = fast_config()
    world = PalmAndArm(tilt_deg, offset_mm, config.jog_period_s)
    at_lift = []
    outcome = ScriptedOperator(world, config, feedback=feedback).grasp_and_lift(
        on_lift=lambda: at_lift.append(world.true_pattern())
    )
    return outcome, at_lift, world


@pytest.mark.slow
@settings(max_examples=15, deadline=None)  # a second a trial; the task bench runs hundreds
@given(st.floats(-35.0, 35.0), st.floats(-4.0, 4.0))
def test_with_a_truthful_palm_every_rack_placement_ends_in_a_correct_grasp(tilt, offset):
    outcome, at_lift, _ = run_trial(tilt, offset)
    assert outcome.lifted, outcome
    assert at_lift == [TARGET_PATTERN], (outcome.attempts, at_lift)
    assert len(outcome.attempts) <= 6


def test_without_feedback_it_closes_once_and_lifts_whatever_it_holds():
    outcome, at_lift, world = run_trial(30.0, 0.0, feedback=False)
    assert outcome.lifted and outcome.attempts == []
    assert at_lift != [TARGET_PATTERN], "a 30 deg lean is not fixed by luck"
    assert world.commands.count("gripper_close") == 1


@pytest.mark.slow
def test_a_lean_is_turned_out_and_an_offset_shifted_out():
    outcome, at_lift, _ = run_trial(30.0, 0.0)
    felt = [a.felt_pattern for a in outcome.attempts]
    assert felt[0] // 3 == 3, f"a 30 deg lean reads as 135 deg first: {felt}"
    assert at_lift == [TARGET_PATTERN]
    outcome, at_lift, _ = run_trial(0.0, -3.8)
    assert outcome.attempts[0].felt_pattern == pattern_of(2, 1)  # 90 deg left
    assert at_lift == [TARGET_PATTERN]


@pytest.mark.parametrize("pattern", range(N_PATTERNS))
def test_every_mask_reads_as_itself(pattern):
    assert read_palm(MASKS[pattern] * 3.0) == pattern
    assert says_lift(MASKS[pattern] * 3.0) == (pattern == TARGET_PATTERN)


def test_partial_bands_are_read_upright_and_lift_needs_two_centre_points():
    one = np.zeros((3, 3))
    one[2, 0] = 2.0  # one point, bottom left: 45 deg centre or 90 deg left
    assert read_palm(one) == pattern_of(2, 1)
    centre_one = np.zeros((3, 3))
    centre_one[1, 1] = 2.0
    assert not says_lift(centre_one), "one point in the middle says nothing about the angle"
    centre_two = MASKS[TARGET_PATTERN] * 2.0
    centre_two[0, 1] = 0.0
    assert says_lift(centre_two)
    bent = MASKS[TARGET_PATTERN] * 2.0
    bent[0, 1], bent[0, 2] = 0.0, 2.0  # the top point off to the right: a "/" lean
    assert not says_lift(bent)
    assert lean_and_side(bent)[0] == 1


@given(hnp.arrays(np.float64, (3, 3), elements=st.floats(allow_nan=True, allow_infinity=True)))
def test_any_stimulus_reads_as_a_pattern_or_nothing(stimulus):
    p = read_palm(stimulus)
    assert p is None or 0 <= p < N_PATTERNS
    lean, side = lean_and_side(stimulus)
    assert lean in (-1, 0, 1) and math.isfinite(side)
    assert says_lift(stimulus) in (True, False)
