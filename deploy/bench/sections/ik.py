"""Section: inverse kinematics, closed form against numerical solvers and float32."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from deploy.bench.fmt import IMG_DIR, num, pct, pyplot, results_of, save_figure, sci, table
from deploy.bench.section import Context, Results, Section

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
        ik_grid_mm=0.5,
        ik_shell_points=2000,
        ik_numeric_points=100,
        ik_calls=1000,
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
    from deploy.bench.ik import ik_tradeoff

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
