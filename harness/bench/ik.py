"""Inverse kinematics: the closed form against numerical solvers, float32 against float64.

Round-trip error is |FK(IK(p)) - p| in mm with the project's float64
forward kinematics, over the contact points the mapping can produce, a
dense grid of the whole workspace, and a thin shell around its edge (found
by bisecting between each reachable grid point and an unreachable
neighbour, so it follows every piece of the boundary: outer reach, inner
reach and the working-mode limit).

The numerical solvers are what one would write without the closed form:
Newton's method on forward kinematics (pure Python, finite-difference
Jacobian) and scipy's ``least_squares``; both start from the retract pose,
as a controller without a previous solution would. A solver can land on
another assembly mode whose FK still returns the target: "same pose" counts
the solutions within 1e-6 rad of the closed form's.

As a bench section: inverse kinematics, closed form against numerical solvers and float32.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from harness.bench.fmt import IMG_DIR, num, pct, pyplot, results_of, save_figure, sci, table
from harness.bench.section import Context, Results, Section
from harness.bench.timing import summarize_ns, time_calls, time_interleaved
from operator_side.palm.contact import ContactMapping, reachable_set
from operator_side.palm.linkglide import (
    DEFAULT_GEOMETRY,
    LinkageGeometry,
    UnreachableTargetError,
    forward_kinematics,
    inverse_kinematics,
    inverse_kinematics_one,
    solve_linkages,
)

log = logging.getLogger(__name__)

#: the three contact points of a typical stimulus (one per linkage), mm
TYPICAL_POINTS = ((-8.0, 58.0), (10.0, 61.0), (28.0, 55.0))
SHELL_DEPTHS_MM = (1e-9, 1e-6, 1e-3, 1e-2, 1e-1)


# ---------------------------------------------------------------- solvers
def reachable_mask(points: np.ndarray, g: LinkageGeometry = DEFAULT_GEOMETRY) -> np.ndarray:
    """Which points the closed form accepts (the project's own test of reach and mode)."""
    with np.errstate(invalid="ignore", over="ignore"):
        _, ok = solve_linkages(np.asarray(points, dtype=np.float64), g)
    return np.asarray(ok)


def ik_float32(points: np.ndarray, g: LinkageGeometry = DEFAULT_GEOMETRY) -> np.ndarray:
    """The same closed form evaluated in float32 throughout (no reach checks)."""
    p = np.asarray(points, dtype=np.float32)
    f = np.float32

    def side(x: np.ndarray, y: np.ndarray, link: float, distal: float) -> tuple:
        d = np.hypot(x, y)
        lk, ds = f(link), f(distal)
        area = np.sqrt(np.maximum((lk + d + ds) * (lk + d - ds) * (ds - lk + d) * (ds + lk - d), 0))
        gamma = np.arctan2(area, (lk - ds) * (lk + ds) + d * d)
        return np.arctan2(y, x), gamma

    x, y = p[..., 0], p[..., 1]
    pa, ga = side(x, y, g.l2, g.l3)
    pe, ge = side(x - f(g.l1), y, g.l5, g.l4)
    pi = f(np.pi)
    ta = pi - np.mod(pi - (pa + ga), f(2 * np.pi))
    te = pi - np.mod(pi - (pe - ge), f(2 * np.pi))
    return np.stack([ta, te], axis=-1)


def _fk_one(ta: float, te: float, g: LinkageGeometry) -> tuple[float, float]:
    """Scalar forward kinematics, same formulas as linkglide.forward_kinematics."""
    bx, by = g.l2 * math.cos(ta), g.l2 * math.sin(ta)
    dx, dy = g.l1 + g.l5 * math.cos(te), g.l5 * math.sin(te)
    vx, vy = dx - bx, dy - by
    dist = math.hypot(vx, vy)
    if dist == 0:
        return math.nan, math.nan
    ux, uy = vx / dist, vy / dist
    a = ((dist - g.l4) * (dist + g.l4) + g.l3 * g.l3) / (2 * dist)
    h = math.sqrt(max((g.l3 - a) * (g.l3 + a), 0.0))
    sign = 1.0 if vx >= 0 else -1.0
    return bx + a * ux - sign * h * uy, by + a * uy + sign * h * ux


def newton_one(
    x: float,
    y: float,
    start: tuple[float, float],
    g: LinkageGeometry = DEFAULT_GEOMETRY,
    tol_mm: float = 1e-12,
    max_iter: int = 50,
) -> tuple[float, float, bool]:
    """Newton on FK(tau) = (x, y) with a central-difference Jacobian; (ta, te, converged)."""
    ta, te = start
    h = 1e-7
    for _ in range(max_iter):
        cx, cy = _fk_one(ta, te, g)
        rx, ry = cx - x, cy - y
        if math.hypot(rx, ry) < tol_mm:
            return ta, te, True
        ax1, ay1 = _fk_one(ta + h, te, g)
        ax0, ay0 = _fk_one(ta - h, te, g)
        ex1, ey1 = _fk_one(ta, te + h, g)
        ex0, ey0 = _fk_one(ta, te - h, g)
        j11, j21 = (ax1 - ax0) / (2 * h), (ay1 - ay0) / (2 * h)
        j12, j22 = (ex1 - ex0) / (2 * h), (ey1 - ey0) / (2 * h)
        det = j11 * j22 - j12 * j21
        if not math.isfinite(det) or det == 0:
            return ta, te, False
        ta -= (j22 * rx - j12 * ry) / det
        te -= (-j21 * rx + j11 * ry) / det
    cx, cy = _fk_one(ta, te, g)
    return ta, te, math.hypot(cx - x, cy - y) < tol_mm * 1e3


def least_squares_one(
    x: float, y: float, start: tuple[float, float], g: LinkageGeometry = DEFAULT_GEOMETRY
) -> tuple[float, float, bool]:
    from scipy.optimize import least_squares

    def residual(t: np.ndarray) -> list[float]:
        cx, cy = _fk_one(float(t[0]), float(t[1]), g)
        return [cx - x, cy - y]

    r = least_squares(residual, np.array(start), xtol=1e-15, ftol=1e-15, gtol=1e-15)
    return float(r.x[0]), float(r.x[1]), bool(r.success)


def _wrap(t: np.ndarray) -> np.ndarray:
    return np.pi - np.mod(np.pi - t, 2 * np.pi)


# ------------------------------------------------------------- geometry sets
def workspace_grid(step_mm: float, g: LinkageGeometry = DEFAULT_GEOMETRY) -> np.ndarray:
    """Every grid point the closed form accepts, over the linkage's bounding box."""
    reach = max(g.l2 + g.l3, g.l5 + g.l4)
    xs = np.arange(-reach, g.l1 + reach + step_mm, step_mm)
    ys = np.arange(-reach, reach + step_mm, step_mm)
    kept = []
    for y in ys:  # row by row: bounded memory at fine steps
        row = np.stack([xs, np.full_like(xs, y)], axis=1)
        kept.append(row[reachable_mask(row, g)])
    return np.concatenate(kept)


def edge_shell(
    step_mm: float, max_points: int, seed: int, g: LinkageGeometry = DEFAULT_GEOMETRY
) -> tuple[np.ndarray, np.ndarray]:
    """Points just inside the boundary, and just outside it, at SHELL_DEPTHS_MM.

    Returns (inside, outside): arrays (n, depths, 2).
    """
    reach = max(g.l2 + g.l3, g.l5 + g.l4)
    xs = np.arange(-reach, g.l1 + reach + step_mm, step_mm)
    ys = np.arange(-reach, reach + step_mm, step_mm)
    # row by row: bounded memory at fine steps
    ok = np.stack([reachable_mask(np.stack([xs, np.full_like(xs, y)], axis=1), g) for y in ys])
    pairs_in, pairs_out = [], []
    for dy, dx in ((0, 1), (1, 0), (0, -1), (-1, 0)):
        nb = np.roll(ok, (-dy, -dx), axis=(0, 1))
        edge = ok & ~nb
        iy, ix = np.nonzero(edge)
        iy2, ix2 = (iy + dy) % ok.shape[0], (ix + dx) % ok.shape[1]
        pairs_in.append(np.stack([xs[ix], ys[iy]], axis=1))
        pairs_out.append(np.stack([xs[ix2], ys[iy2]], axis=1))
    a, b = np.concatenate(pairs_in), np.concatenate(pairs_out)
    if len(a) > max_points:
        pick = np.random.default_rng(seed).choice(len(a), max_points, replace=False)
        a, b = a[pick], b[pick]
    lo, hi = a.copy(), b.copy()
    for _ in range(60):  # bisection to the last bit
        mid = 0.5 * (lo + hi)
        m = reachable_mask(mid, g)
        lo[m] = mid[m]
        hi[~m] = mid[~m]
    direction = (b - a) / np.linalg.norm(b - a, axis=1, keepdims=True)
    depths = np.array(SHELL_DEPTHS_MM)[None, :, None]
    inside = lo[:, None, :] - depths * direction[:, None, :]
    outside = hi[:, None, :] + depths * direction[:, None, :]
    return inside, outside


# --------------------------------------------------------------- round trips
def round_trip_mm(points: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """|FK(angles) - points| per point; NaN where FK refuses the angles."""
    out = np.full(len(points), np.nan)
    chunk = 200_000
    for s in range(0, len(points), chunk):
        p, a = points[s : s + chunk], np.asarray(angles[s : s + chunk], dtype=np.float64)
        finite = np.isfinite(a).all(axis=1)
        try:
            c = forward_kinematics(a[finite])
            out[s : s + chunk][finite] = np.hypot(*(c - p[finite]).T)
        except UnreachableTargetError:
            idx = np.flatnonzero(finite)
            for k in idx:
                try:
                    c = forward_kinematics(a[k])
                    out[s + k] = math.hypot(c[0] - p[k, 0], c[1] - p[k, 1])
                except UnreachableTargetError:
                    pass
    return out


def _err_summary(err: np.ndarray) -> dict[str, Any]:
    finite = np.isfinite(err)
    return {
        "points": int(err.size),
        "max_mm": float(err[finite].max()) if finite.any() else None,
        "p99_mm": float(np.percentile(err[finite], 99)) if finite.any() else None,
        "median_mm": float(np.median(err[finite])) if finite.any() else None,
        "fk_refused": int((~finite).sum()),
    }


def _three(fn: Callable[[float, float], Any]) -> Callable[[int], None]:
    """One call per linkage at the typical stimulus's three contact points."""

    def call(_i: int) -> None:
        for x, y in TYPICAL_POINTS:
            fn(x, y)

    return call


def _time_three(fn: Callable[[float, float], Any], calls: int) -> dict[str, float]:
    return summarize_ns(time_calls(_three(fn), calls, warmup=min(20, calls))).as_dict()


def ik_tradeoff(
    grid_step_mm: float,
    shell_points: int,
    numeric_points: int,
    calls: int,
    seed: int = 5,
    least_squares: bool = True,
) -> dict[str, Any]:
    """Time for three linkages and round-trip error per method, on each point set."""
    g = DEFAULT_GEOMETRY
    operational = reachable_set(ContactMapping())
    grid = workspace_grid(grid_step_mm, g)
    inside, outside = edge_shell(grid_step_mm, shell_points, seed, g)
    shell = inside.reshape(-1, 2)
    # where the boundary bends within a step, a point "inside" can still be out: drop it
    shell = shell[reachable_mask(shell, g)]
    closed = inverse_kinematics(grid)
    closed_shell = inverse_kinematics(shell)
    retract = inverse_kinematics_one(*ContactMapping().retract_point_mm)
    rng = np.random.default_rng(seed)
    sub = np.concatenate(
        [
            grid[rng.choice(len(grid), min(numeric_points // 2, len(grid)), replace=False)],
            shell[rng.choice(len(shell), min(numeric_points // 2, len(shell)), replace=False)],
        ]
    )
    sub_ref = inverse_kinematics(sub)
    methods: list[dict[str, Any]] = []

    # closed form, float64, scalar (the operator's hot path)
    methods.append(
        {
            "method": "closed form, float64, scalar (inverse_kinematics_one)",
            "key": "closed_scalar_f64",
            "time_3": None,
            "operational": _err_summary(
                round_trip_mm(
                    operational, np.array([inverse_kinematics_one(*p) for p in operational])
                )
            ),
            "grid": _err_summary(round_trip_mm(grid, closed)),
            "shell": _err_summary(round_trip_mm(shell, closed_shell)),
            "same_pose": 1.0,
        }
    )
    three = np.array(TYPICAL_POINTS)
    methods.append(
        {
            "method": "closed form, float64, NumPy (inverse_kinematics)",
            "key": "closed_numpy_f64",
            "time_3": None,
            "operational": _err_summary(
                round_trip_mm(operational, inverse_kinematics(operational))
            ),
            "grid": _err_summary(round_trip_mm(grid, closed)),
            "shell": _err_summary(round_trip_mm(shell, closed_shell)),
            "same_pose": 1.0,
        }
    )
    three32 = three.astype(np.float32)
    f32_grid = ik_float32(grid)
    methods.append(
        {
            "method": "closed form, float32, NumPy",
            "key": "closed_numpy_f32",
            "time_3": None,
            "operational": _err_summary(round_trip_mm(operational, ik_float32(operational))),
            "grid": _err_summary(round_trip_mm(grid, f32_grid)),
            "shell": _err_summary(round_trip_mm(shell, ik_float32(shell))),
            "same_pose": float(
                np.mean(np.abs(_wrap(f32_grid.astype(np.float64) - closed)).max(axis=1) < 1e-3)
            ),
            "same_pose_tolerance_rad": 1e-3,
        }
    )
    numeric: list[tuple[str, str, Callable[..., tuple[float, float, bool]]]] = [
        ("Newton on FK (pure Python, finite-difference Jacobian)", "newton", newton_one)
    ]
    if least_squares:
        try:
            import scipy.optimize  # noqa: F401

            numeric.append(
                ("scipy.optimize.least_squares on FK", "least_squares", least_squares_one)
            )
        except ImportError:
            log.warning("scipy is not installed: no least_squares row")
    for name, key, solver in numeric:
        n_calls = calls if key == "newton" else max(20, calls // 20)
        sols = [solver(x, y, retract, g) for x, y in sub]
        ang = np.array([[s[0], s[1]] for s in sols])
        ang = _wrap(ang)
        converged = np.array([s[2] for s in sols])
        err = round_trip_mm(sub, ang)
        op_sols = np.array([solver(x, y, retract, g)[:2] for x, y in operational])
        methods.append(
            {
                "method": name,
                "key": key,
                "time_3": _time_three(lambda x, y, s=solver: s(x, y, retract, g), n_calls)
                if key == "least_squares"
                else None,
                "operational": _err_summary(round_trip_mm(operational, _wrap(op_sols))),
                "grid_and_shell_sample": _err_summary(err),
                "converged_share": float(converged.mean()),
                "same_pose": float(np.mean(np.abs(_wrap(ang - sub_ref)).max(axis=1) < 1e-6)),
                "sample_points": len(sub),
            }
        )
    # the fast methods take turns call by call: the load's drift is shared by all
    timers: dict[str, Callable[[int], Any]] = {
        "closed_scalar_f64": _three(lambda x, y: inverse_kinematics_one(x, y, g)),
        "closed_numpy_f64": lambda _i: inverse_kinematics(three, g),
        "closed_numpy_f32": lambda _i: ik_float32(three32, g),
        "newton": _three(lambda x, y: newton_one(x, y, retract, g)),
    }
    times = time_interleaved(list(timers.values()), calls, warmup=min(50, calls))
    by_key = dict(zip(timers, times, strict=True))
    for m in methods:
        if m["time_3"] is None:
            m["time_3"] = summarize_ns(by_key[m["key"]]).as_dict()
    # outside the edge: every method must refuse (the scalar path is the one that runs)
    out_pts = outside.reshape(-1, 2)
    accepted = 0
    for x, y in out_pts[:: max(1, len(out_pts) // 5000)]:
        try:
            inverse_kinematics_one(float(x), float(y), g)
            accepted += 1
        except UnreachableTargetError:
            pass
    return {
        "geometry": {k: getattr(g, k) for k in ("l1", "l2", "l3", "l4", "l5")},
        "grid_step_mm": grid_step_mm,
        "grid_points": len(grid),
        "shell_points": len(shell),
        "shell_depths_mm": list(SHELL_DEPTHS_MM),
        "operational_points": len(operational),
        "typical_points": [list(p) for p in TYPICAL_POINTS],
        "methods": methods,
        "outside_edge_checked": len(out_pts[:: max(1, len(out_pts) // 5000)]),
        "outside_edge_accepted_by_scalar": accepted,
    }


TITLE = "Run time against error: inverse kinematics"


@dataclass(frozen=True)
class IkSizes:
    ik_grid_mm: float  # step of the workspace grid
    ik_shell_points: int
    ik_numeric_points: int  # sample the numerical solvers run on
    ik_calls: int
    ik_least_squares: bool  # scipy's solver: slow to time


SIZES = {
    "full": IkSizes(
        ik_grid_mm=0.05,
        ik_shell_points=20000,
        ik_numeric_points=2000,
        ik_calls=5000,
        ik_least_squares=True,
    ),
    "quick": IkSizes(
        ik_grid_mm=1.0,
        ik_shell_points=500,
        ik_numeric_points=30,
        ik_calls=300,
        ik_least_squares=True,
    ),
    "smallest": IkSizes(
        ik_grid_mm=2.0,
        ik_shell_points=200,
        ik_numeric_points=10,
        ik_calls=50,
        ik_least_squares=False,
    ),
}


def measure(ctx: Context, sizes: IkSizes) -> dict[str, Any]:
    return ik_tradeoff(
        sizes.ik_grid_mm,
        sizes.ik_shell_points,
        sizes.ik_numeric_points,
        sizes.ik_calls,
        least_squares=sizes.ik_least_squares,
    )


def markdown(results: Results) -> list[str]:
    s = results_of(results, "ik")
    out = ["", f"## {TITLE}", ""]
    if s is None:
        return [*out, "Not run."]
    out += [
        f"Time: three linkages at a typical stimulus's contact points. Round-trip error "
        f"|FK(IK(p)) - p| (mm, float64 FK) over the {s['operational_points']} points the "
        f"contact mapping can produce, a {s['grid_step_mm']} mm grid of the whole workspace "
        f"({s['grid_points']:,} points) and a shell inside its edge ({s['shell_points']:,} "
        f"points at {', '.join(f'{d:g}' for d in s['shell_depths_mm'])} mm from the boundary). "
        "Numerical solvers start from the retract pose and are run on a sample of grid and "
        "shell points.",
        "",
    ]
    rows = []
    for mth in s["methods"]:
        gs = mth.get("grid") or mth.get("grid_and_shell_sample")
        sh = mth.get("shell")
        rows.append(
            [
                mth["method"],
                num(mth["time_3"]["median_us"]),
                num(mth["time_3"]["p99_us"]),
                sci(mth["operational"]["max_mm"]),
                sci(gs["max_mm"]),
                sci(gs["p99_mm"]),
                sci(sh["max_mm"]) if sh else "(in the sample)",
                pct(mth.get("converged_share", 1.0)),
                pct(mth["same_pose"]),
            ]
        )
    out += table(
        [
            "method",
            "median (us)",
            "p99 (us)",
            "max error, contact points (mm)",
            "max error, grid (mm)",
            "p99 error, grid (mm)",
            "max error, edge shell (mm)",
            "converged",
            "same pose as closed form",
        ],
        rows,
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    )
    out += [
        "",
        f"Outside the edge: {s['outside_edge_checked']:,} points just beyond the boundary "
        f"given to `inverse_kinematics_one`; accepted: {s['outside_edge_accepted_by_scalar']} "
        "(the rest raise `UnreachableTargetError`, as they must). In float32, a point near the "
        "working-mode limit (B, C and D nearly in line) can round onto the other circle "
        "intersection, so FK returns the other solution: that is the large float32 maximum, "
        "not a precision loss of a few ulps.",
        "",
        f"![IK]({IMG_DIR}/bench_ik.png)",
    ]
    return out


def figure(result: dict[str, Any], path: Path) -> Path:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8, 4.6))
    sets = (
        ("operational", "o", "contact points"),
        ("grid", "s", "workspace grid"),
        ("shell", "^", "edge shell"),
        ("grid_and_shell_sample", "D", "grid + shell sample"),
    )
    colors = {m["key"]: f"C{k}" for k, m in enumerate(result["methods"])}
    for m in result["methods"]:
        t = m["time_3"]["median_us"]
        for key, marker, _ in sets:
            if key in m and m[key]["max_mm"] is not None:
                ax.scatter(
                    t,
                    max(m[key]["max_mm"], 1e-16),
                    marker=marker,
                    s=55,
                    color=colors[m["key"]],
                    alpha=0.85,
                )
    handles = [
        plt.Line2D([], [], color=colors[m["key"]], marker="o", ls="", label=m["key"])
        for m in result["methods"]
    ] + [plt.Line2D([], [], color="grey", marker=mk, ls="", label=lb) for _, mk, lb in sets]
    ax.legend(handles=handles, fontsize=8, loc="center right")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("time for three linkages, median (us, one core)")
    ax.set_ylabel("largest round-trip error |FK(IK(p)) - p| (mm)")
    ax.set_title("IK: time against round-trip error")
    ax.grid(alpha=0.3, which="both")
    return save_figure(fig, path)


SECTION = Section(
    name="ik",
    title=TITLE,
    sizes=SIZES,
    measure=measure,
    markdown=markdown,
    figure=figure,
)
