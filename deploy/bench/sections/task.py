"""Section: the task benchmark, does the palm help an operator grasp a pipette right?"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

from deploy.bench.fmt import results_of
from deploy.bench.section import Context, Results, Section, Verdict

TITLE = "The task: grasp a pipette at 90 deg, centre, and lift it"

#: the seed of the trials' placements (the same placements in every cell)
TRIAL_SEED = 2026


@dataclass(frozen=True)
class TaskSizes:
    trials: int  # per cell
    scenarios: tuple[str, ...]
    feedbacks: tuple[str, ...]
    # Cells side by side. One on 2 cores: three (a world, a robot node, a link simulator and
    # an operator each) drove the load to 11 and arms missed their targets in time.
    parallel_cells: int = 1


ALL = (("lan", "intercontinental", "bad_day"), ("mask", "direct", "none"))
SIZES = {
    "full": TaskSizes(50, *ALL),
    "quick": TaskSizes(5, *ALL),
    "smallest": TaskSizes(1, ("lan",), ("none",)),  # the plumbing; tests/lab checks the task
}


def measure(ctx: Context, sizes: TaskSizes) -> dict[str, Any]:
    from concurrent.futures import ThreadPoolExecutor

    from deploy.bench.task import LIFTED_MM, OFFSET_RANGE_M, TILT_RANGE_DEG, run_cell, trial_setups
    from deploy.bench.timing import machine_load

    setups = trial_setups(TRIAL_SEED, sizes.trials)
    load_before = machine_load()
    plan = [(scenario, feedback) for scenario in sizes.scenarios for feedback in sizes.feedbacks]
    t0 = time.monotonic()
    with ThreadPoolExecutor(max_workers=sizes.parallel_cells) as pool:
        cells = list(pool.map(lambda cell: run_cell(*cell, setups), plan))
    return {
        "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
        "seed": TRIAL_SEED,
        "trials_per_cell": sizes.trials,
        "tilt_range_deg": TILT_RANGE_DEG,
        "offset_range_mm": OFFSET_RANGE_M * 1000,
        "lifted_mm": LIFTED_MM,
        "cells": cells,
        "load_before": load_before,
        "load_after": machine_load(),
        "parallel_cells": sizes.parallel_cells,
        "wall_s": round(time.monotonic() - t0, 1),
    }


def _rate(summary: dict[str, Any]) -> str:
    lo, hi = summary["success_ci95"]
    rate = summary["success_rate"]
    if rate is None:
        return "-"
    return f"{rate * 100:.0f} % ({lo * 100:.0f}-{hi * 100:.0f})"


def _s(value: float | None) -> str:
    return "-" if value is None else f"{value:.1f}"


def verdicts(results: Results) -> list[Verdict]:
    """The palm helps: in every scenario, both feedback conditions beat none."""
    s = results_of(results, "task")
    if s is None:
        return []
    by = {(c["scenario"], c["feedback"]): c["summary"] for c in s["cells"]}
    out = []
    for scenario in dict.fromkeys(c["scenario"] for c in s["cells"]):
        none = by.get((scenario, "none"))
        for feedback in ("mask", "direct"):
            cell = by.get((scenario, feedback))
            if cell is None or none is None or not cell["trials"]:
                continue
            out.append(
                Verdict(
                    f"{scenario}: {feedback} feedback succeeds more often than none",
                    f"{cell['successes']}/{cell['trials']} against "
                    f"{none['successes']}/{none['trials']}",
                    cell["successes"] > none["successes"],
                    table=None,
                )
            )
    return out


def markdown(results: Results) -> list[str]:
    """The table per scenario and feedback; nothing when the section did not run."""
    s = results_of(results, "task")
    if not s:
        return []
    from operator_side.scripted import ScriptedOperatorConfig

    cfg = ScriptedOperatorConfig()
    minutes = s.get("wall_s", sum(c["cell_s"] for c in s["cells"])) / 60
    side_by_side = s.get("parallel_cells", 1)
    lines = [
        "",
        f"## {TITLE}",
        "",
        "A scripted operator (`operator_side/scripted.py`) works through the operator node "
        "and the link simulator on the simulated lab (`deploy/bench/task.py`). Each trial "
        "puts the rack's one pipette at a tilt it does not know (uniform in "
        f"+-{s['tilt_range_deg']:g} deg) and an offset along the rack (+-"
        f"{s['offset_range_mm']:g} mm); it lowers the open gripper, closes, feels the palm "
        "and, unless the palm presses two or three points all on the centre line (90 deg "
        "centre), opens, turns the wrist or shifts the fingers as the palm says, and tries "
        f"again (at most {cfg.max_attempts} grasps); then it lifts "
        f"{cfg.lift_m * 1000:g} mm along the tool's axis. Without feedback it closes once "
        "and lifts. A trial succeeds when the world's ground truth at the decision to lift is "
        f"90 deg centre and the pipette comes at least {s['lifted_mm']:g} mm out of its hole. "
        "Time to a correct grasp runs from the trial's start to that decision (successes "
        f"only). {s['trials_per_cell']} trials per cell, the same seeded placements (seed "
        f"{s['seed']}) in every cell; 95 % Wilson intervals. Measured {s['date']}, load "
        f"(1 min) {s['load_before']['loadavg_1m']} before and "
        f"{s['load_after']['loadavg_1m']} after, on 2 shared cores; the run took "
        f"{minutes:.0f} minutes"
        + (f", {side_by_side} cells side by side." if side_by_side > 1 else "."),
        "",
        "| link | feedback | success (95 % CI) | correct grasps | time to correct p50 s "
        "| p90 s | grasps per trial | slip in the pads p50 / max mm | errors |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for c in s["cells"]:
        m = c["summary"]
        lines.append(
            f"| {c['scenario']} | {c['feedback']} | {_rate(m)} | {m['correct_grasps']} | "
            f"{_s(m['time_to_correct_s_p50'])} | {_s(m['time_to_correct_s_p90'])} | "
            f"{_s(m['attempts_mean'])} | {_s(m.get('slip_mm_p50'))} / "
            f"{_s(m.get('slip_mm_max'))} | {m['errors']} |"
        )
    lines += [
        "",
        "`mask`: the robot's CNN picks the pattern and the palm presents its mask over the "
        "downsized frame (the paper's method); `direct`: the frame downsized, no CNN; `none`: "
        "the operator ignores the palm. The operator names what it feels by the nearest of "
        "the twelve masks (a partial band is assumed upright), so `direct` feedback is read "
        "with the same rule. Slip: how much less than the tool the pipette rose over the "
        "correct grasps (the tool's rise read from the robot's heartbeat pose). "
        "Rerun: `deepxpalm bench --only task`.",
    ]
    return lines


SECTION = Section(
    name="task",
    title=TITLE,
    sizes=SIZES,
    measure=measure,
    markdown=markdown,
    verdicts=verdicts,
)
