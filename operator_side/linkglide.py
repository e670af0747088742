"""LinkGlide's inverted five-bar linkages: geometry, inverse and forward kinematics.

One linkage, in its own plane (mm, rad): base joints A = (0, 0) and
E = (l1, 0); the servo at A turns l2 (A to B) to tau_a, the servo at E turns
l5 (E to D) to tau_e, both counter-clockwise from +X, reported in (-pi, pi].
l3 joins B to C and l4 joins D to C. Working mode "elbows out": B left of
A->C, D right of E->C; forward kinematics takes the circle intersection with
the larger Y.

Inverse kinematics, by the law of cosines on each side:
    tau_a = atan2(Y, X) + gamma_a,    tau_e = atan2(Y, X - l1) - gamma_e,
    gamma = atan2(sqrt((l+d+m)(l+d-m)(m-l+d)(m+l-d)), l^2 + d^2 - m^2)
with (l, m, d) = (l2, l3, |C - A|) or (l5, l4, |C - E|). This is the root
of D cos(tau) + E sin(tau) + H = 0 chosen by the working mode. The paper's
half-angle form (its equations 1 and 2) prints H^2 + E^2 - D^2 under the
square root where D^2 + E^2 - H^2 belongs, and divides by H - D, which
vanishes inside the workspace; the form above has neither hazard, and the
factored square root keeps full precision at the workspace edge.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from common.config import param

#: A point this close outside the reach of a side is taken as on its edge, so a
#: target computed onto the edge is not refused for a rounding error.
EDGE_TOLERANCE_MM = 1e-10


class UnreachableTargetError(ValueError):
    """No elbows-out pose of the linkage reaches this contact point."""


@dataclass(frozen=True)
class LinkageGeometry:
    """Link lengths in mm. Defaults are the project's for a device of the published size."""

    l1: float = param(20.0, "distance between the two base joints A and E")
    l2: float = param(30.0, "proximal link driven by the A servo")
    l3: float = param(45.0, "distal link from B to the contact point C")
    l4: float = param(45.0, "distal link from D to the contact point C")
    l5: float = param(30.0, "proximal link driven by the E servo")

    def __post_init__(self) -> None:
        for name in ("l1", "l2", "l3", "l4", "l5"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"link length {name} must be a positive number, not {value!r}")


DEFAULT_GEOMETRY = LinkageGeometry()


def _wrap(angle: np.ndarray) -> np.ndarray:
    """Into (-pi, pi]."""
    return np.pi - np.mod(np.pi - angle, 2 * np.pi)


def _wrap_one(angle: float) -> float:
    wrapped = math.remainder(angle, 2 * math.pi)
    return math.pi if wrapped == -math.pi else wrapped


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


def inverse_kinematics_one(
    x: float, y: float, g: LinkageGeometry = DEFAULT_GEOMETRY
) -> tuple[float, float]:
    """Scalar fast path for the 60 Hz loop (about 1 us; NumPy's per-call cost is 20x that).

    Same formulas and checks as ``inverse_kinematics``.
    """
    if not (math.isfinite(x) and math.isfinite(y)):
        raise UnreachableTargetError(f"contact point ({x!r}, {y!r}) mm is not finite")
    taus = []
    for bx0, link, distal, sign in ((0.0, g.l2, g.l3, 1.0), (g.l1, g.l5, g.l4, -1.0)):
        px = x - bx0
        d = math.hypot(px, y)
        f2, f3, f4 = link + d - distal, distal - link + d, distal + link - d
        if d <= 0 or min(f2, f3, f4) < -EDGE_TOLERANCE_MM:
            raise UnreachableTargetError(
                f"contact point ({x!r}, {y!r}) mm is not reachable by linkage {g}"
            )
        area = math.sqrt((link + d + distal) * max(f2, 0.0) * max(f3, 0.0) * max(f4, 0.0))
        gamma = math.atan2(area, (link - distal) * (link + distal) + d * d)
        taus.append(math.atan2(y, px) + sign * gamma)
    ta, te = (_wrap_one(t) for t in taus)
    bx, by = g.l2 * math.cos(ta), g.l2 * math.sin(ta)
    dx, dy = g.l1 + g.l5 * math.cos(te), g.l5 * math.sin(te)
    cross = (dx - bx) * (y - by) - (dy - by) * (x - bx)
    if (cross < 0) if dx - bx >= 0 else (cross > 0):
        raise UnreachableTargetError(
            f"contact point ({x!r}, {y!r}) mm needs the other assembly mode of linkage {g}"
        )
    return ta, te
