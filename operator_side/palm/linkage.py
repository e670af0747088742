"""One LinkGlide linkage in plain numbers: its geometry and its inverse kinematics.

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

No NumPy here: the 60 Hz loop solves one linkage at a time (NumPy's per-call
cost is many times the arithmetic), and ``deepxpalm palm lift`` computes the
retract pose with these very functions, in a process whose start-up is the
time a dead operator node's linkages stay on the palm. The array forms are
in ``operator_side.palm.linkglide``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from common.config.typed import param

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


def wrap_one(angle: float) -> float:
    """Into (-pi, pi]."""
    wrapped = math.remainder(angle, 2 * math.pi)
    return math.pi if wrapped == -math.pi else wrapped


def inverse_kinematics_one(
    x: float, y: float, g: LinkageGeometry = DEFAULT_GEOMETRY
) -> tuple[float, float]:
    """Scalar fast path for the 60 Hz loop (about 1 us; NumPy's per-call cost is 20x that).

    Same formulas and checks as ``operator_side.palm.linkglide.inverse_kinematics``.
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
    ta, te = (wrap_one(t) for t in taus)
    bx, by = g.l2 * math.cos(ta), g.l2 * math.sin(ta)
    dx, dy = g.l1 + g.l5 * math.cos(te), g.l5 * math.sin(te)
    cross = (dx - bx) * (y - by) - (dy - by) * (x - bx)
    if (cross < 0) if dx - bx >= 0 else (cross > 0):
        raise UnreachableTargetError(
            f"contact point ({x!r}, {y!r}) mm needs the other assembly mode of linkage {g}"
        )
    return ta, te
