"""LinkGlide's inverted five-bar linkages over arrays: inverse and forward kinematics.

The geometry, the working mode and the inverse kinematics' derivation are in
``operator_side.palm.linkage``, which solves one linkage in plain numbers (the 60 Hz
loop and ``deepxpalm palm lift`` use it); here the same formulas run over
arrays of points, and forward kinematics takes the circle intersection with
the larger Y.
"""

from __future__ import annotations

import numpy as np

# the scalar pieces, re-exported: one linkage's geometry and inverse kinematics
from operator_side.palm.linkage import (  # noqa: F401
    DEFAULT_GEOMETRY,
    EDGE_TOLERANCE_MM,
    LinkageGeometry,
    UnreachableTargetError,
    inverse_kinematics_one,
)


def _wrap(angle: np.ndarray) -> np.ndarray:
    """Into (-pi, pi]."""
    return np.pi - np.mod(np.pi - angle, 2 * np.pi)


def _side_angle(
    x: np.ndarray, y: np.ndarray, link: float, distal: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(direction to C, elbow angle gamma, reachable?) for one side's base at the origin."""
    d = np.hypot(x, y)
    f1 = link + d + distal
    f2 = link + d - distal
    f3 = distal - link + d
    f4 = distal + link - d
    ok = (f2 >= -EDGE_TOLERANCE_MM) & (f3 >= -EDGE_TOLERANCE_MM) & (f4 >= -EDGE_TOLERANCE_MM)
    ok &= d > 0
    area = np.sqrt(
        np.where(ok, f1 * np.maximum(f2, 0) * np.maximum(f3, 0) * np.maximum(f4, 0), 0.0)
    )
    gamma = np.arctan2(area, (link - distal) * (link + distal) + d * d)
    return np.arctan2(y, x), gamma, ok


def solve_linkages(points: np.ndarray, g: LinkageGeometry) -> tuple[np.ndarray, np.ndarray]:
    """Both motor angles per point, and which points are reachable (no error raised)."""
    x = points[..., 0]
    y = points[..., 1]
    psi_a, gamma_a, ok_a = _side_angle(x, y, g.l2, g.l3)
    psi_e, gamma_e, ok_e = _side_angle(x - g.l1, y, g.l5, g.l4)
    tau_a = _wrap(psi_a + gamma_a)
    tau_e = _wrap(psi_e - gamma_e)
    # The pose must be the one forward kinematics returns: C is the circle
    # intersection with the larger Y. B and D are computed exactly as
    # forward_kinematics computes them, so both sides agree on the branch
    # even where the two intersections' Y differ by a rounding error.
    bx, by = g.l2 * np.cos(tau_a), g.l2 * np.sin(tau_a)
    dx, dy = g.l1 + g.l5 * np.cos(tau_e), g.l5 * np.sin(tau_e)
    cross = (dx - bx) * (y - by) - (dy - by) * (x - bx)
    ok_mode = np.where(dx - bx >= 0, cross >= 0, cross <= 0)
    ok = ok_a & ok_e & ok_mode & np.isfinite(x) & np.isfinite(y)
    return np.stack([tau_a, tau_e], axis=-1), ok


def inverse_kinematics(points: np.ndarray, geometry: LinkageGeometry | None = None) -> np.ndarray:
    """Contact points (..., 2) in mm -> servo angles (..., 2) (tau_a, tau_e) in radians.

    Raises ``UnreachableTargetError`` naming the first point that no
    elbows-out pose reaches, or that is not finite.
    """
    g = geometry or DEFAULT_GEOMETRY
    pts = np.asarray(points, dtype=np.float64)
    if pts.shape[-1:] != (2,):
        raise ValueError(f"points must have shape (..., 2), not {pts.shape}")
    with np.errstate(invalid="ignore", over="ignore"):
        angles, ok = solve_linkages(pts, g)
    if not np.all(ok):
        bad = np.argwhere(~np.asarray(ok))[0] if pts.ndim > 1 else ()
        point = pts[tuple(bad)] if pts.ndim > 1 else pts
        raise UnreachableTargetError(
            f"contact point ({point[0]!r}, {point[1]!r}) mm is not reachable by an "
            f"elbows-out pose of linkage {g}"
        )
    return angles


def forward_kinematics(angles: np.ndarray, geometry: LinkageGeometry | None = None) -> np.ndarray:
    """Servo angles (..., 2) in radians -> contact points (..., 2) in mm.

    Raises ``UnreachableTargetError`` when the distal links cannot close.
    """
    g = geometry or DEFAULT_GEOMETRY
    ang = np.asarray(angles, dtype=np.float64)
    if ang.shape[-1:] != (2,):
        raise ValueError(f"angles must have shape (..., 2), not {ang.shape}")
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        ta, te = ang[..., 0], ang[..., 1]
        bx, by = g.l2 * np.cos(ta), g.l2 * np.sin(ta)
        dx, dy = g.l1 + g.l5 * np.cos(te), g.l5 * np.sin(te)
        vx, vy = dx - bx, dy - by
        dist = np.hypot(vx, vy)
        ux, uy = vx / dist, vy / dist
        a = ((dist - g.l4) * (dist + g.l4) + g.l3 * g.l3) / (2 * dist)
        h2 = (g.l3 - a) * (g.l3 + a)
        ok = np.isfinite(h2) & (h2 >= -1e-9 * g.l3 * g.l3) & (dist > 0)
        h = np.sqrt(np.maximum(h2, 0.0))
        sign = np.where(vx >= 0, 1.0, -1.0)
        cx = bx + a * ux - sign * h * uy
        cy = by + a * uy + sign * h * ux
    if not np.all(ok):
        bad = np.argwhere(~np.asarray(ok))[0] if ang.ndim > 1 else ()
        pair = ang[tuple(bad)] if ang.ndim > 1 else ang
        raise UnreachableTargetError(
            f"angles ({pair[0]!r}, {pair[1]!r}) rad do not close linkage {g}"
        )
    return np.stack([cx, cy], axis=-1)
