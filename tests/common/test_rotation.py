"""Rotation vectors round-trip exactly at, near and across pi, where the UR's tool-down pose is.

The UR3e's tool-down pose is a half turn (the dashboard shows rx = ry = 127.3
deg, a magnitude of pi): the arm simulator and the scripted operator convert
it back and forth on every step, so an error there is an error in every pose
they report.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from common.rotation import matrix_to_rotvec, rotation_angle, rotvec_to_matrix

TOLERANCE_RAD = 1e-12
TOOL_DOWN = np.array([math.pi / math.sqrt(2), math.pi / math.sqrt(2), 0.0])


def canonical(r: np.ndarray) -> np.ndarray:
    """The same turn with magnitude in [0, pi]: what matrix_to_rotvec answers."""
    theta = float(np.linalg.norm(r))
    if theta == 0.0:
        return r
    wrapped = math.remainder(theta, 2 * math.pi)  # in [-pi, pi]
    return r / theta * wrapped if wrapped >= 0 else -r / theta * -wrapped


def round_trip_error(r: np.ndarray) -> float:
    """How far the vector comes back, in radians; at magnitude pi, r and -r are one turn."""
    back = matrix_to_rotvec(rotvec_to_matrix(r))
    want = canonical(r)
    error = float(np.linalg.norm(back - want))
    if abs(float(np.linalg.norm(want)) - math.pi) < 1e-9:
        error = min(error, float(np.linalg.norm(back + want)))
    return error


def test_the_tool_down_pose_round_trips_exactly() -> None:
    assert round_trip_error(TOOL_DOWN) < TOLERANCE_RAD
    m = rotvec_to_matrix(TOOL_DOWN)
    np.testing.assert_allclose(m @ [0, 0, 1], [0, 0, -1], atol=1e-15)  # the tool points down
    # the case hypothesis found against the old threshold: magnitude about pi, 5e-7 lost
    found = np.array([0.0, 2.41, 2.01])
    for theta in (math.pi, math.pi - 1e-7, math.pi - 1e-6, math.pi - 2e-6):
        assert round_trip_error(found / np.linalg.norm(found) * theta) < TOLERANCE_RAD


@pytest.mark.slow
def test_hundred_thousand_vectors_at_near_and_across_pi() -> None:
    rng = np.random.default_rng(2026)
    n = 100_000
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    offsets = np.concatenate(
        [
            np.zeros(n // 5),  # exactly pi
            rng.choice([-1e-15, 1e-15, -2e-15, 2e-15, -4e-16, 4e-16], n // 5),  # an ulp or so
            rng.uniform(-1e-6, 1e-6, n // 5),  # where the old threshold switched
            rng.uniform(-0.5, 0.5, n // 5),  # near, and across into (pi, 2pi)
            rng.uniform(-math.pi, 3 * math.pi, n - 4 * (n // 5)),  # anywhere, several turns
        ]
    )
    worst = 0.0
    for axis, offset in zip(axes, offsets, strict=True):
        worst = max(worst, round_trip_error(axis * (math.pi + offset)))
    assert worst < TOLERANCE_RAD, f"worst round trip error {worst:.3g} rad"


def test_small_turns_keep_their_digits() -> None:
    for theta in (0.0, 1e-300, 1e-15, 1e-9, 1e-8, 1.0000001e-8, 1e-4):
        r = np.array([0.6, -0.8, 0.0]) * theta
        back = matrix_to_rotvec(rotvec_to_matrix(r))
        assert np.linalg.norm(back - r) <= max(1e-16, 1e-12 * theta)


finite_vectors = st.lists(
    st.floats(-20.0, 20.0, allow_nan=False, allow_infinity=False), min_size=3, max_size=3
).map(np.array)


@given(finite_vectors)
def test_any_vector_round_trips(r: np.ndarray) -> None:
    assert round_trip_error(r) < TOLERANCE_RAD


@given(finite_vectors, finite_vectors)
def test_matrices_are_rotations_and_compose_as_turns(a: np.ndarray, b: np.ndarray) -> None:
    ma, mb = rotvec_to_matrix(a), rotvec_to_matrix(b)
    np.testing.assert_allclose(ma @ ma.T, np.eye(3), atol=1e-14)
    assert abs(np.linalg.det(ma) - 1.0) < 1e-14
    angle = rotation_angle(ma, mb)
    assert 0.0 <= angle <= math.pi + 1e-15
    # the angle from a to b is the magnitude of the turn that takes a to b
    turn = matrix_to_rotvec(mb @ ma.T)
    assert abs(angle - float(np.linalg.norm(turn))) < TOLERANCE_RAD
    np.testing.assert_allclose(rotvec_to_matrix(turn) @ ma, mb, atol=1e-13)
