"""Five-bar kinematics: IK then FK returns the target to 1e-9 mm, everywhere reachable."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from operator_side.palm.linkglide import (
    DEFAULT_GEOMETRY,
    EDGE_TOLERANCE_MM,
    LinkageGeometry,
    UnreachableTargetError,
    forward_kinematics,
    inverse_kinematics,
    inverse_kinematics_one,
)

G = DEFAULT_GEOMETRY


def _reachable(x: float, y: float, g: LinkageGeometry = G) -> bool:
    try:
        inverse_kinematics(np.array([x, y]), g)
    except UnreachableTargetError:
        return False
    return True


def test_spec_defaults_and_unreachable_error_is_a_value_error():
    assert (G.l1, G.l2, G.l3, G.l4, G.l5) == (20, 30, 45, 45, 30)
    assert issubclass(UnreachableTargetError, ValueError)
    with pytest.raises(UnreachableTargetError, match=r"\(200"):
        inverse_kinematics(np.array([[10.0, 50.0], [200.0, 0.0]]))


def test_known_pose_matches_geometry():
    # Symmetric point above the middle of the base: mirror-symmetric angles.
    ta, te = inverse_kinematics(np.array([10.0, 58.0]))
    assert math.isclose(ta + te, math.pi, abs_tol=1e-12)
    # elbows out: B left of A->C, D right of E->C
    bx, by = 30 * math.cos(ta), 30 * math.sin(ta)
    dx, dy = 20 + 30 * math.cos(te), 30 * math.sin(te)
    assert 10.0 * by - 58.0 * bx > 0
    assert (10.0 - 20) * dy - 58.0 * (dx - 20) < 0


@pytest.mark.slow
@pytest.mark.untimed  # no timing checked
def test_whole_workspace_grid_round_trips():
    xs, ys = np.meshgrid(np.linspace(-80, 100, 721), np.linspace(-80, 100, 721))
    pts = np.stack([xs, ys], -1).reshape(-1, 2)
    ok = np.array([_reachable(*p) for p in pts[::97]])  # sanity: both kinds exist
    assert ok.any() and not ok.all()
    from operator_side.palm.linkglide import solve_linkages

    angles, mask = solve_linkages(pts, G)
    back = forward_kinematics(angles[mask])
    assert np.abs(back - pts[mask]).max() < 1e-9


@pytest.mark.slow
@pytest.mark.untimed  # no timing checked
@settings(suppress_health_check=[HealthCheck.filter_too_much])
@given(st.floats(-55, 75), st.floats(-20, 75))
def test_round_trip_property(x, y):
    assume(_reachable(x, y))
    angles = inverse_kinematics(np.array([x, y]))
    assert np.all((angles > -math.pi) & (angles <= math.pi))
    back = forward_kinematics(angles)
    assert abs(back[0] - x) < 1e-9 and abs(back[1] - y) < 1e-9
    fast = inverse_kinematics_one(x, y)
    assert abs(fast[0] - angles[0]) < 1e-12 and abs(fast[1] - angles[1]) < 1e-12


@pytest.mark.slow
@pytest.mark.untimed  # no timing checked
@given(st.floats(0, 2 * math.pi), st.one_of(st.just(0.0), st.floats(-1e-6, 1e-6)))
def test_round_trip_at_the_outer_edge(theta, eps):
    # |C - A| = l2 + l3: the A side fully stretched.
    r = G.l2 + G.l3 + eps
    x, y = r * math.cos(theta), r * math.sin(theta)
    if not _reachable(x, y):
        # only beyond the edge (or refused by the other side or the assembly
        # mode, which then refuses the points just inside too)
        assert eps > EDGE_TOLERANCE_MM / 2 or not _reachable(x / r * (r - 1e-3), y / r * (r - 1e-3))
        return
    back = forward_kinematics(inverse_kinematics(np.array([x, y])))
    assert np.abs(back - [x, y]).max() < 1e-9


@given(st.floats(0, 2 * math.pi), st.floats(-1e-6, 1e-6))
def test_round_trip_at_the_inner_edge(theta, eps):
    r = abs(G.l3 - G.l2) + eps
    x, y = G.l1 + r * math.cos(theta), r * math.sin(theta)
    if _reachable(x, y):
        back = forward_kinematics(inverse_kinematics(np.array([x, y])))
        assert np.abs(back - [x, y]).max() < 1e-9


def test_beyond_reach_raises():
    with pytest.raises(UnreachableTargetError):
        inverse_kinematics(np.array([0.0, G.l2 + G.l3 + 1e-6]))
    with pytest.raises(UnreachableTargetError):
        inverse_kinematics_one(0.0, G.l2 + G.l3 + 1e-6)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_points_raise(bad):
    with pytest.raises(UnreachableTargetError):
        inverse_kinematics(np.array([bad, 50.0]))
    with pytest.raises(UnreachableTargetError):
        inverse_kinematics_one(10.0, bad)


def test_paper_printed_equation_is_wrong_and_ours_is_right():
    # The paper's eq. (1) with H^2 + E^2 - D^2 under the root, for a point where it is defined.
    x, y = 10.0, 58.0
    d, e = -2 * x * G.l2, -2 * y * G.l2
    h = G.l2**2 + x**2 + y**2 - G.l3**2
    printed = 2 * math.atan((-e + math.sqrt(h * h + e * e - d * d)) / (h - d))
    ours = inverse_kinematics_one(x, y)[0]
    # ours satisfies the constraint D cos + E sin + H = 0; the printed one does not
    assert abs(d * math.cos(ours) + e * math.sin(ours) + h) < 1e-9
    assert abs(d * math.cos(printed) + e * math.sin(printed) + h) > 1.0
