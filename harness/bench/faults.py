"""Section: the fault matrix, every deployed process killed, frozen and restarted.

The table goes into docs/robustness.md between its markers as well as into
the bench's report; ``harness/faults/`` runs it.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from harness.bench.doc_block import replace_block
from harness.bench.fmt import results_of
from harness.bench.section import Context, Results, Section, Verdict

TITLE = "Fault matrix"
BEGIN = "<!-- faults table: begin (deepxpalm bench --only faults --update-docs) -->"
END = "<!-- faults table: end -->"


@dataclass(frozen=True)
class FaultsSizes:
    fault_cells: str  # a name in harness.faults.matrix.MATRICES


SIZES = {
    "full": FaultsSizes(fault_cells="full"),  # every process x every fault: about 25 minutes
    "quick": FaultsSizes(fault_cells="quick"),  # the safety cells: about 3 minutes
    "smallest": FaultsSizes(fault_cells="smallest"),  # one cell
}


def measure(ctx: Context, sizes: FaultsSizes) -> dict[str, Any]:
    """Every cell, with the bench's pin to one core lifted: these are whole deployments."""
    from harness.bench.stamp import git_commit
    from harness.bench.timing import machine_load, original_affinity
    from harness.faults.matrix import MATRICES, run_cells

    cells = MATRICES[sizes.fault_cells]()
    pinned = os.sched_getaffinity(0)
    os.sched_setaffinity(0, original_affinity())
    try:
        load_before = machine_load()
        rows = run_cells(cells, progress=_cell_ended(ctx, cells))
        load_after = machine_load()
    finally:
        os.sched_setaffinity(0, pinned)
    return {
        "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
        "commit": git_commit(),
        "load_before": load_before,
        "load_after": load_after,
        "cells": rows,
    }


def _cell_ended(ctx: Context, cells: list[Any]) -> Callable[[str], None]:
    """The matrix's word per cell ended, as the bench's progress (its row is in the report)."""
    done = [0]

    def ended(line: str) -> None:
        done[0] += 1
        ctx.steps(done[0], len(cells), "cells", cells[done[0] - 1].label)

    return ended


def _s(x: float | None) -> str:
    return "-" if x is None else f"{x * 1e3:.0f} ms" if x < 1 else f"{x:.1f} s"


#: the processes whose failure cuts the operator's jogs off the arm: the stop budget applies
CUTS_THE_JOG = ("robot", "arm", "operator", "router", "netsim", "link")


def _cruising(row: dict[str, Any]) -> bool:
    """Whether the arm was at the jog's speed when the fault came (a run before the cells
    checked it has no speed: a stop within 50 ms, faster than any path, says it was not)."""
    speed, still = row.get("arm_speed_at_fault_m_s"), row["arm_still_s"]
    if speed is None:
        return still is None or still >= 0.05
    return speed >= 0.015


def _late(row: dict[str, Any]) -> bool:
    from harness.faults.matrix import ARM_STILL_BUDGET_S, back_before_a_stop_was_due, whole_again_s

    still = row["arm_still_s"]
    back = whole_again_s(row["recovered_s"], row.get("link_back_s"))
    if back_before_a_stop_was_due(still, back, row.get("arm_rest_s")):
        return False
    return row["target"] in CUTS_THE_JOG and (still is None or still > ARM_STILL_BUDGET_S)


def _arm(row: dict[str, Any]) -> str:
    from harness.faults.matrix import back_before_a_stop_was_due, whole_again_s

    if not _cruising(row):
        return "(not moving at the fault: the machine's load had stalled the jog)"
    still, away = row["arm_still_s"], row.get("arm_unreadable_s")
    if still is None:
        if _late(row):
            return "**kept moving**"
        cut = row["target"] in CUTS_THE_JOG  # a device or video fault leaves the jog whole
        back = whole_again_s(row["recovered_s"], row.get("link_back_s"))
        if cut and back_before_a_stop_was_due(still, back, row.get("arm_rest_s")):
            return "slowed; the link was back before a stop was due"
        return "kept following the jog"
    if away is not None and away <= still:
        return f"controller unreadable from {_s(away)} (an interruption)"
    if row["target"] not in CUTS_THE_JOG:
        return f"stopped at {_s(still)} (an interruption)"
    return f"{_s(still)}" + (" **over budget**" if _late(row) else "")


def _palm(row: dict[str, Any]) -> str:
    from harness.faults.matrix import KILL, PALM_LIFT_BUDGET_S, RESTART, STOP, UNPLUG

    off = row["palm_off_s"]
    if row["target"] == "operator" and row["fault"] in (KILL, STOP):
        # physical: the process that lifts the palm is the one that failed; servos hold
        why = "no: the operator node lifts it, and it failed (servos hold their last goal)"
        return why if off is None else f"{why}; off at {_s(off)}, by the restarted node"
    if row["target"] == "servos" and row["fault"] in (KILL, RESTART, UNPLUG):
        why = "no: the bus itself failed (no goal reaches a servo)"
        return why if off is None else f"{why}; off at {_s(off)}, once it was back"
    if off is None:
        return "stayed on (stimuli kept coming)"
    return f"yes, {_s(off)}" if off <= PALM_LIFT_BUDGET_S else f"**late**, {_s(off)}"


def _gripper(row: dict[str, Any]) -> str:
    held = row["gripper_held"]
    if held is None:
        return "no reading: its own process died"
    return "held" if held else f"**opened** (to {row['gripper_min_pos']:.0f})"


def _recovered(row: dict[str, Any]) -> str:
    rec = row["recovered_s"]
    if rec is None:
        return "**no** (not within 30 s)"
    if row["arm_still_s"] is None and row["palm_off_s"] is None:
        return "never interrupted"
    return _s(rec)


def _recording(row: dict[str, Any]) -> str:
    if not row["recording_ok"]:
        return f"**no** ({row['recording_records']} records)"
    return f"yes (to {_s(row['recording_gap_s'])} before)"


def table(section: dict[str, Any]) -> list[str]:
    out = [
        "| process | fault | restarted by | arm still after | gripper | palm lifted | "
        "everything back | arm still after letting go | recording up to the fault |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for row in section["cells"]:
        if row.get("error"):
            first = row["error"].splitlines()[0]
            out.append(f"| {row['target']} | {row['fault']} | | **cell failed: {first}** |||||")
            continue
        released = row["released_still_s"]
        out.append(
            f"| {row['target']} | {row['fault']} | {row['restarted_by']} | {_arm(row)} | "
            f"{_gripper(row)} | {_palm(row)} | {_recovered(row)} | "
            f"{'**still moving**' if released is None else _s(released)} | {_recording(row)} |"
        )
    before, after = section["load_before"]["loadavg_1m"], section["load_after"]["loadavg_1m"]
    commit = section.get("commit") or "?"
    out += [
        "",
        f"Measured {section['date']} at commit {commit}, machine load (1 min) {before} before "
        f"and {after} after, {len(section['cells'])} cells.",
    ]
    return out


def verdicts(results: Results) -> list[Verdict]:
    """The issue's: no cell leaves the arm moving or the gripper open."""
    r = results_of(results, "faults")
    if r is None:
        return []
    rows = [c for c in r["cells"] if not c.get("error")]
    moving = [c for c in rows if c["released_still_s"] is None]
    late = [c for c in rows if _late(c)]
    opened = [c for c in rows if c["gripper_held"] is False]
    failed = [c for c in r["cells"] if c.get("error")]
    bad = moving + late + opened
    measured = (
        f"{len(rows)} cells: {len(late)} with the arm still late, {len(moving)} left moving, "
        f"{len(opened)} with the gripper open, {len(failed)} failed to run"
    )
    return [
        Verdict(
            "fault matrix: no cell leaves the arm moving or the gripper open; the arm still "
            "within 400 ms when a failure cuts the operator's jogs off",
            measured,
            not bad and not failed,
        )
    ]


def markdown(results: Results) -> list[str]:
    r = results_of(results, "faults")
    out = ["", f"## {TITLE}", ""]
    if r is None:
        return [*out, "Not run."]
    return [*out, "What each column means: docs/robustness.md, Fault matrix.", "", *table(r)]


def update_robustness_doc(section: dict[str, Any], out_dir: Path) -> list[Path]:
    """docs/robustness.md carries the table between its markers."""
    page = out_dir / "robustness.md"
    if not page.exists() or "error" in section:
        return []
    replace_block(page, BEGIN, END, table(section))
    return [page]


SECTION = Section(
    name="faults",
    title=TITLE,
    sizes=SIZES,
    measure=measure,
    markdown=markdown,
    verdicts=verdicts,
    update_other_docs=update_robustness_doc,
    quick=False,
)
