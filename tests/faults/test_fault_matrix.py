"""The fault matrix's safety cells as tests: real processes, read from outside the one that fails.

Each cell is a whole deployment (router, robot and operator nodes, netsim,
video, recorder, and the four device simulators as processes of their own)
with an operator jogging and holding a grasp; ``harness/faults/matrix.py``
injects the fault and reads the arm from the UR simulator, the gripper from
its socket and the palm from the servo bus. The bounds are the product's
budgets widened for a loaded machine; each message says which it was: a
stop that never came is the product, a late one is compared with the same
cell's own stop after the operator let go (the node's deadman, measured in
the same run under the same load).
"""

from __future__ import annotations

import pytest

from harness.faults.deployment import ARM_PROCESS, DeploymentError
from harness.faults.matrix import (
    ARM_STILL_BUDGET_S,
    PALM_LIFT_BUDGET_S,
    RELEASE_WAIT_S,
    Cell,
    back_before_a_lift_could_show,
    back_before_a_stop_was_due,
    quick_matrix,
    run_cell,
)

#: how much a loaded machine may add to a budget before the test calls it the product's fault
LOAD_SLACK_S = 0.6

#: the robot node's own kill -9 and SIGSTOP are held, ten trials each, by
#: tests/system/test_node_death.py (arm from the controller, gripper from its
#: simulator); here the cells that cut the link instead, where the node's deadman acts,
#: and the arm process killed, where the controller's watchdog acts
CELLS = [c for c in quick_matrix() if c.target != "robot"]


@pytest.fixture(scope="module")
def retract_goals() -> list[int]:
    from operator_side.palm.renderer import LinkGlideRenderer, RendererConfig
    from operator_side.servos.feetech import FeetechConfig

    return LinkGlideRenderer(RendererConfig(), FeetechConfig().calibration).retract_goals


@pytest.mark.slow
@pytest.mark.parametrize("cell", CELLS, ids=lambda c: c.label.replace(" ", "_"))
def test_the_arm_stops_and_the_gripper_holds(cell: Cell, retract_goals: list[int]) -> None:
    try:
        row = run_cell(cell, retract_goals)
    except DeploymentError as e:
        pytest.fail(f"the deployment never got ready (load, or a start-up failure): {e}")
    assert row.stop_s is None or "killed" not in row.restarted_by, (
        f"{cell.label}: the process ignored SIGTERM for {row.stop_s:.0f} s and had to be killed "
        "(product: a clean stop must stop it; it kept running meanwhile)"
    )
    baseline = row.released_still_s
    assert baseline is not None, (
        f"{cell.label}: the arm had not come to rest {RELEASE_WAIT_S:.0f} s after the operator "
        f"let go at the end; the longest stretch without a reading of it: "
        f"{row.released_silence_s} s (product: nothing stopped it, unless the arm's probe "
        f"read nothing); {row}\n{row.log_tails}"
    )
    if back_before_a_stop_was_due(row.arm_still_s, row.whole_again_s, row.arm_rest_s, LOAD_SLACK_S):
        print(
            f"{cell.label}: the link was back in {row.whole_again_s:.2f} s, before a stop could "
            f"show as one (the arm at rest at {row.arm_rest_s} s)"
        )
    else:
        assert row.arm_still_s is not None, (
            f"{cell.label}: the arm never stopped while the path of its commands was broken "
            f"(product: nothing outside the failed process stops it); {row}\n{row.log_tails}"
        )
        assert row.arm_still_s <= ARM_STILL_BUDGET_S + LOAD_SLACK_S, (
            f"{cell.label}: the arm was still {row.arm_still_s * 1e3:.0f} ms after the fault, "
            f"budget {ARM_STILL_BUDGET_S * 1e3:.0f} ms; the node's own deadman stop in the same "
            f"cell took {baseline * 1e3:.0f} ms (if that is late too, the machine is loaded; if "
            f"not, the product is slow to stop); {row.notes}\n{row.log_tails}"
        )
    assert row.gripper_held, (
        f"{cell.label}: the gripper opened to {row.gripper_min_pos} during the fault (product: "
        "the pipette must never drop because a process died)"
    )
    assert row.recovered_s is not None, (
        f"{cell.label}: 30 s after the fault the palm or the arm still did not work again with no "
        f"human (product: a restart or reconnect that never happens); {row}\n{row.log_tails}"
    )
    assert row.recording_ok, f"{cell.label}: the recording up to the fault did not read back"
    if cell.target == ARM_PROCESS:
        return  # the pads' stream does not pass through the arm process: the palm stays on
    if row.palm_off_s is None and back_before_a_lift_could_show(row.link_back_s):
        print(
            f"{cell.label}: netsim forwarded again {row.link_back_s} s after the fault, before "
            "the palm's lift could show (stale after 0.15 s, then 0.1 s of travel)"
        )
        return
    assert row.palm_off_s is not None and row.palm_off_s <= PALM_LIFT_BUDGET_S + LOAD_SLACK_S, (
        f"{cell.label}: the palm lifted off {row.palm_off_s} s after the fault, budget "
        f"{PALM_LIFT_BUDGET_S * 1e3:.0f} ms (None: never, the product's staleness limit failed; "
        f"the operator's loop woke at most {row.operator_late_ms} ms late"
        f"{', across the link gap' if row.operator_starved_through_gap else ''}: a palm that "
        "stays pressed on a dead link is the product failing, a busy machine or not); netsim "
        f"forwarding again {row.link_back_s} s after the fault; {row}\n{row.palm_trace}\n"
        f"{row.log_tails}"
    )
