"""The band's finer angle: what the assist turns by, on frames the synthetic pads make."""

from __future__ import annotations

import dataclasses

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from common.synthetic_tactile import SyntheticTactileModel
from common.tactile import FRAME_SHAPE, pattern_of
from robot_side.perception.band_angle import band_angle_deg


def _errors(position_class: int) -> np.ndarray:
    """|estimate - truth| (deg, on the 180 deg circle) over a sweep of angles and grips."""
    rng = np.random.default_rng(7)
    out = []
    for seed in range(3):
        model = SyntheticTactileModel(seed=seed)
        for theta in np.arange(0.0, 180.0, 2.5):
            angle_class = round(float(theta) / 45) % 4
            grasp = model.draw_grasp(pattern_of(angle_class, position_class), rng)
            grasp = dataclasses.replace(grasp, theta_deg=float(theta))
            for level in (4, 16, 28):
                got = band_angle_deg(model.grasp_frame(grasp, level, rng))
                if got is not None:
                    out.append(abs((got - theta + 90.0) % 180.0 - 90.0))
    return np.array(out)


def test_the_band_angle_is_within_a_few_degrees_of_the_grasps_own():
    """A class is 45 deg wide; the assist needs the angle to a few degrees to aim at 90."""
    for position_class in (0, 1, 2):
        err = _errors(position_class)
        assert len(err) > 0.95 * 3 * 72 * 3, "the band had no angle in too many frames"
        p50, p90 = np.median(err), np.percentile(err, 90)
        assert p50 < 2.0 and p90 < 6.0, (position_class, p50, p90, err.max())
        assert err.max() < 35.0, (position_class, err.max())  # inside band_agrees_deg


@settings(max_examples=300, deadline=None)
@given(
    arrays(
        np.float32,
        FRAME_SHAPE,
        elements=st.floats(width=32, allow_nan=True, allow_infinity=True),
    )
)
def test_any_frame_gives_an_angle_in_range_or_none_never_an_error(frame):
    got = band_angle_deg(frame)
    assert got is None or (np.isfinite(got) and 0.0 <= got < 180.0)


def test_a_round_blob_or_a_blank_frame_has_no_angle():
    blank = np.zeros(FRAME_SHAPE, np.float32)
    assert band_angle_deg(blank) is None
    blob = blank.copy()
    blob[:, 4:6, 4:6] = 2.0
    assert band_angle_deg(blob) is None
    column = blank.copy()
    column[:, :, 4] = 2.0  # along a column: 90 deg
    assert band_angle_deg(column) == 90.0
