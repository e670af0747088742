"""The task benchmark's trial, through everything: does the palm's feedback fix a grasp?

The robot node (its own process, the real drivers on the lab world), the link
simulator and the operator node with the scripted operator, as
`deepxpalm bench --only task` runs them. A pipette standing 6 mm to the
left of where the operator reaches: without feedback the operator grasps it
off-centre; with the palm it feels "90 deg left", shifts and lifts it centred.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from pathlib import Path

import pytest

pytest.importorskip("mujoco", reason="the simulated lab needs the 'lab' extra (MuJoCo)")
pytest.importorskip("rtde_control", reason="the lab's arm is driven through ur-rtde")

from common.tactile.contract import classes_of, pattern_of
from harness.bench.task import LIFTED_MM, TrialSetup, run_cell
from robot_side.node.config import AssistConfig

pytestmark = [
    pytest.mark.slow,
    pytest.mark.timeout(240),
    pytest.mark.usefixtures("quiet_gc"),
    # the world (MuJoCo and the UR controller in one interpreter) keeps real time only on a
    # core no deployment lane keeps busy: beside three deployments and two busy loops its
    # controller stopped answering for 0.5-1 s, and the trials judged the machine
    pytest.mark.serial,
]

OFF_CENTRE = TrialSetup(index=0, tilt_deg=0.0, offset_m=-0.006)


def _trial(feedback: str, setup: TrialSetup, workdir: Path, check: Callable[[dict], None]):
    """One trial of ``feedback`` from fresh processes, held to ``check``, on its first run.

    The arm's keep-alive runs in the arm process, real-time where granted
    (docs/arm.md): a busy machine must not make the controller's watchdog
    stop the arm, so a trip fails the trial.
    """
    cell = run_cell("lan", feedback, [setup], workdir=workdir / feedback)
    assert not cell["errors"], cell["errors"]
    (trial,) = cell["trials"]
    assert not trial["watchdog_trips"], (
        f"the controller's watchdog stopped the robot {trial['watchdog_trips']} time(s): the "
        f"arm's keep-alive was starved past its window: {trial}"
    )
    check(trial)


def test_the_palm_turns_an_off_centre_grasp_into_a_correct_lift(tmp_path):
    _trial("mask", OFF_CENTRE, tmp_path, _turned_into_a_correct_lift)


def _turned_into_a_correct_lift(trial: dict) -> None:
    assert "error" not in trial, f"the trial did not reach its lift: {trial['error']}"
    _report_clock(trial)
    assert trial["felt"][0] == pattern_of(2, 1), f"felt 90 deg left first: {trial}"
    assert trial["felt_truth"][0] == pattern_of(2, 1), "and the world agrees"
    assert trial["success"], trial
    assert trial["truth"] == "90 deg centre" and trial["lifted_mm"] >= LIFTED_MM


def test_without_feedback_the_same_grasp_is_lifted_off_centre(tmp_path):
    _trial("none", OFF_CENTRE, tmp_path, _lifted_off_centre)


def _lifted_off_centre(trial: dict) -> None:
    assert "error" not in trial, f"the trial did not reach its lift: {trial['error']}"
    _report_clock(trial)
    assert not trial["success"] and trial["truth"] == "90 deg left", trial


def _report_clock(trial: dict) -> None:
    """Every trial carries the world's sim/wall; one that fell behind (< 0.98) says so."""
    assert 0 < trial["sim_wall"] <= 1.05 and trial["behind"] == (trial["sim_wall"] < 0.98), trial
    print(f"trial sim/wall {trial['sim_wall']} (slowest 1 s {trial['sim_wall_lowest']})")
    if trial["behind"]:
        warnings.warn(f"the world fell behind real time in this trial: {trial}", stacklevel=2)


TILTED = TrialSetup(index=0, tilt_deg=-30.0, offset_m=0.0)


def test_the_assist_turns_a_45_degree_grasp_to_90_degrees_on_the_robot(tmp_path):
    """The operator feels 45 deg, holds the assist; the robot re-grasps; the palm says 90."""
    _trial("mask_assist", TILTED, tmp_path, _assisted_to_90_degrees)


def _assisted_to_90_degrees(trial: dict) -> None:
    assert "error" not in trial, f"the trial did not reach its lift: {trial['error']}"
    first, after = trial["felt"][0], trial["felt"][1]
    assert first is not None, f"the first grasp was never felt steadily: {trial}"
    assert classes_of(first)[0] == 1, f"felt 45 deg first: {trial}"
    assert classes_of(trial["felt_truth"][0])[0] == 1, f"and the world agrees: {trial}"
    assert after == pattern_of(2, 0) and trial["attempts"] == 2, f"then 90 centre: {trial}"
    assert trial["success"] and trial["truth"] == "90 deg centre", trial
    # the pads saw about 60 deg: a whole-class turn (45) would leave it at 105, "90" by class
    # and 15 deg from the 112.5 deg edge; the band's own angle turns it the 30 it needed. The
    # bound is the assist's own "aligned" (an enable that lapsed mid-turn on a starved PC
    # leaves the rest to that rule: 79 deg once, beside two busy loops)
    within = AssistConfig().aligned_within_deg
    assert abs(trial["truth_tilt_deg"] - 90.0) <= within, f"aligned to 90 deg: {trial}"
    _report_clock(trial)
