"""Section: numerical stress, every output finite and inside its limits whatever comes in."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from deploy.bench.fmt import num, results_of, sci, table
from deploy.bench.section import Context, Results, Section, Verdict

TITLE = "Numerical stress"


@dataclass(frozen=True)
class StressSizes:
    stress_grid_mm: float
    stress_shell_points: int
    stress_stimuli: int  # random stimuli through the servo renderer
    stress_random_frames: int


SIZES = {
    "full": StressSizes(
        stress_grid_mm=0.05,
        stress_shell_points=40000,
        stress_stimuli=200000,
        stress_random_frames=500,
    ),
    "quick": StressSizes(
        stress_grid_mm=0.5, stress_shell_points=2000, stress_stimuli=20000, stress_random_frames=30
    ),
    "smallest": StressSizes(
        stress_grid_mm=2.0, stress_shell_points=200, stress_stimuli=500, stress_random_frames=3
    ),
}


def measure(ctx: Context, sizes: StressSizes) -> dict[str, Any]:
    from deploy.bench.stress import stress

    return stress(
        ctx.classifier,
        sizes.stress_grid_mm,
        sizes.stress_shell_points,
        sizes.stress_stimuli,
        sizes.stress_random_frames,
    )


def verdicts(results: Results) -> list[Verdict]:
    """Zero non-finite outputs: a check any machine must pass, not a timing."""
    st = results_of(results, "stress")
    return [
        Verdict(
            "numerical stress: zero non-finite outputs",
            None if st is None else f"{st['total_nonfinite_outputs']} non-finite",
            None if st is None else st["total_nonfinite_outputs"] == 0,
            table="check",
        )
    ]


def markdown(results: Results) -> list[str]:
    s = results_of(results, "stress")
    out = ["", f"## {TITLE}", ""]
    if s is None:
        return [*out, "Not run."]
    ik, rd, fr = s["ik"], s["renderer"], s["rendering"]
    out += table(
        ["sweep", "inputs", "non-finite outputs", "worst case"],
        [
            [
                f"IK, {ik['grid_step_mm']} mm workspace grid (vector; scalar on "
                f"{ik['grid']['scalar_points']:,})",
                num(ik["grid"]["points"]),
                num(
                    ik["grid"]["nonfinite_angles"]
                    + ik["grid"]["nonfinite_angles_scalar"]
                    + ik["grid"]["nonfinite_counts"]
                ),
                f"round trip {sci(ik['grid']['max_round_trip_mm'])} mm; scalar vs vector "
                f"{sci(ik['grid']['scalar_vs_vector_max_rad'])} rad",
            ],
            [
                "IK, shell inside the workspace edge",
                num(ik["shell"]["points"]),
                num(
                    ik["shell"]["nonfinite_angles"]
                    + ik["shell"]["nonfinite_angles_scalar"]
                    + ik["shell"]["nonfinite_counts"]
                ),
                f"round trip {sci(ik['shell']['max_round_trip_mm'])} mm; FK refused "
                f"{ik['shell']['fk_refused']}",
            ],
            [
                "random stimuli (extreme, negative, NaN, inf) through LinkGlideRenderer",
                num(rd["stimuli"]),
                num(rd["nonfinite_outputs"]),
                f"largest servo step {rd['largest_step_counts']} counts "
                f"({rd['largest_step_deg']:.2f} deg; limit {rd['max_step_counts_allowed']}); "
                f"out of limits {rd['out_of_limits']}; exceptions {rd['exceptions']}",
            ],
            [
                f"frames at floor, saturation, beyond, non-finite ({fr['frames']}) x methods x "
                "orders x masks",
                num(fr["renders_checked"]),
                num(fr["nonfinite_outputs"]),
                f"out of 0..9 N {fr['out_of_range']}; two cells in a row "
                f"{fr['more_than_one_cell_in_a_row']}; refused by the codec "
                f"{fr['refused_by_codec']}; exceptions {fr['exceptions']}; classifier "
                f"non-finite {fr['classifier_nonfinite']}",
            ],
        ],
        "|---|---:|---:|---|",
    )
    out += [
        "",
        f"Total non-finite outputs: **{s['total_nonfinite_outputs']}**. Largest round-trip "
        f"error: {sci(s['largest_round_trip_mm'])} mm. Largest servo step per cycle: "
        f"{s['largest_servo_step_counts']} counts ({_step_limit(rd['max_step_counts_allowed'])}).",
    ]
    return out


def _step_limit(counts: int) -> str:
    """The renderer's per-cycle limit as configured, and what it rounds to in whole counts."""
    import math

    from operator_side.renderer import RendererConfig
    from operator_side.servos.calibration import COUNTS_PER_RAD

    configured = RendererConfig().max_step_deg_per_cycle
    return (
        f"{configured:g} deg rounds to {counts} counts, "
        f"{math.degrees(counts / COUNTS_PER_RAD):.2f} deg"
    )


SECTION = Section(
    name="stress",
    title=TITLE,
    sizes=SIZES,
    measure=measure,
    markdown=markdown,
    verdicts=verdicts,
)
