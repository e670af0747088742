"""Where ``deepxpalm collect`` sends the TCP for each pattern: turned about the fingers' axis."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from common.tactile.synthetic import offset_direction
from robot_side.arm.sim.kinematics import rotvec_to_matrix
from robot_side.perception.collect import CollectConfig, grasp_pose

rotvecs = st.tuples(*[st.floats(-2.5, 2.5)] * 3).map(np.array)


@settings(max_examples=60, deadline=None)
@given(rotvec=rotvecs, pattern=st.integers(0, 11), start_angle=st.sampled_from([0.0, 90.0]))
def test_each_pattern_turns_about_the_closing_axis_and_shifts_across_the_band(
    rotvec, pattern, start_angle
):
    config = CollectConfig(start_angle_deg=start_angle)
    start = np.concatenate([[0.1, -0.2, 0.3], rotvec])
    pose = grasp_pose(start, pattern, config)
    r0, r = rotvec_to_matrix(start[3:]), rotvec_to_matrix(pose[3:])
    assert np.allclose(r[:, 1], r0[:, 1], atol=1e-9), "the closing axis (tool y) stays put"
    angle, position = divmod(pattern, 3)
    turned = math.degrees(math.atan2(np.dot(r[:, 2], r0[:, 0]), np.dot(r[:, 0], r0[:, 0])))
    error = (turned - (45 * angle - start_angle) + 180) % 360 - 180
    assert abs(error) < 1e-6, "the tool turned by the band's change of angle"
    shift = pose[:3] - start[:3] + np.array([0, 0, config.approach_depth_m])
    if position == 0:
        assert np.allclose(shift, 0, atol=1e-12)
    else:
        dx, dy = offset_direction(angle)
        across = -(dx * r[:, 0] + dy * r[:, 2]) * (1 if position == 1 else -1)
        assert np.allclose(shift, across * config.side_offset_mm / 1000, atol=1e-12)
        assert math.isclose(np.linalg.norm(shift), 0.006, rel_tol=1e-9)
