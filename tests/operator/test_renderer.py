"""Whatever the stimulus, the servos get finite counts inside their limits, one step at a time."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from common.errors import ConfigError
from operator_side.palm.contact import ContactMapping, stimulus_to_points
from operator_side.palm.linkglide import forward_kinematics
from operator_side.palm.renderer import LinkGlideRenderer, RendererConfig
from operator_side.servos.calibration import LinkGlideCalibration, ServoCalibration


def renderer(**kw) -> LinkGlideRenderer:
    return LinkGlideRenderer(RendererConfig(**kw), LinkGlideCalibration())


def test_rows_map_to_the_documented_contact_points():
    m = ContactMapping()
    stim = np.array([[0, 0, 0], [0, 1.0, 0], [0, 0, 9.0]], np.float32)
    pts = stimulus_to_points(stim, m)
    assert pts[0] == (10.0, 40.0)  # lifted off
    assert pts[1] == (10.0, 55.0)  # 1 N just touches
    assert pts[2] == (28.0, 61.0)  # 9 N presses 6 mm


def test_target_angles_reach_the_contact_points():
    r = renderer()
    stim = np.array([[4.0, 0, 0], [0, 0, 0], [0, 0, 7.5]], np.float32)
    angles = r.target_angles(stim)
    pts = forward_kinematics(angles)
    np.testing.assert_allclose(pts[0], (-8.0, 55 + 6 * 3 / 8), atol=1e-9)
    np.testing.assert_allclose(pts[1], (10.0, 40.0), atol=1e-9)
    np.testing.assert_allclose(pts[2], (28.0, 55 + 6 * 6.5 / 8), atol=1e-9)


def test_no_stimulus_lifts_every_linkage():
    r = renderer()
    np.testing.assert_array_equal(r.target_counts(None), r.retract_counts)
    np.testing.assert_array_equal(r.target_counts(np.zeros((3, 3))), r.retract_counts)


def test_an_unreachable_mapping_is_refused_at_start():
    with pytest.raises(ConfigError, match="cannot reach"):
        renderer(contact=ContactMapping(column_x_mm=(-80.0, 10.0, 28.0)))


def test_a_jump_becomes_a_rate_limited_motion():
    r = renderer(max_step_deg_per_cycle=4.0)
    current = r.retract_counts.copy()
    target = r.target_counts(np.array([[9, 0, 0], [0, 9, 0], [0, 0, 9]], np.float32))
    steps = 0
    while not np.array_equal(current, target):
        nxt = r.step(current, target)
        assert np.abs(nxt - current).max() <= r.max_step_counts
        current = nxt
        steps += 1
        assert steps < 200
    assert steps > 1


stimuli = hnp.arrays(
    np.float64,
    (3, 3),
    elements=st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.floats(-10, 20)),
)


@pytest.mark.slow
@given(stimuli, st.floats(-5, 5, allow_nan=False))
def test_any_stimulus_gives_safe_counts(stim, fraction):
    cal = LinkGlideCalibration(
        servos=[
            ServoCalibration(
                id=i,
                zero_counts=2048,
                direction=-1 if i % 2 else 1,
                min_counts=1500,
                max_counts=2600,
            )
            for i in range(1, 7)
        ]
    )
    r = LinkGlideRenderer(RendererConfig(), cal)
    target = r.target_counts(stim)
    assert target.dtype == np.int64
    assert cal.within_limits(target)
    nxt = r.step(r.retract_counts, target, fraction)
    assert cal.within_limits(nxt)
    assert np.abs(nxt - r.retract_counts).max() <= r.max_step_counts


def test_non_finite_angles_never_become_counts():
    cal = LinkGlideCalibration()
    with pytest.raises(ValueError):
        cal.angles_to_counts(np.array([[math.nan, 0], [0, 0], [0, 0]]))
