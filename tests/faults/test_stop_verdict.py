"""When a fault cell may excuse a missing stop: the link came back before one could show."""

from __future__ import annotations

from harness.faults.matrix import ARM_STILL_BUDGET_S, STILL_FOR_S, back_before_a_stop_was_due


def test_a_link_back_within_the_budget_needs_no_stop():
    assert back_before_a_stop_was_due(None, ARM_STILL_BUDGET_S - 0.05)


def test_a_link_back_just_after_the_budget_needs_the_arm_at_rest_in_time():
    back = ARM_STILL_BUDGET_S + STILL_FOR_S / 2  # too soon for a still stretch to complete
    assert back_before_a_stop_was_due(None, back, arm_rest_s=ARM_STILL_BUDGET_S - 0.1)
    assert not back_before_a_stop_was_due(None, back, arm_rest_s=None)  # never at rest
    assert not back_before_a_stop_was_due(None, back, arm_rest_s=ARM_STILL_BUDGET_S + 0.02)
    assert back_before_a_stop_was_due(None, back, ARM_STILL_BUDGET_S + 0.02, slack_s=0.1)


def test_a_link_down_long_enough_to_see_a_stop_is_judged_by_the_stop():
    late = ARM_STILL_BUDGET_S + STILL_FOR_S + 0.05
    assert not back_before_a_stop_was_due(None, late, arm_rest_s=0.1)
    assert not back_before_a_stop_was_due(0.3, 0.2)  # it stopped: judged as a stop
    assert not back_before_a_stop_was_due(None, None)  # never back


def test_a_fault_that_never_cut_the_jog_is_not_called_a_link_that_came_back():
    from harness.bench.faults import _arm

    row = {
        "arm_speed_at_fault_m_s": 0.03,
        "arm_still_s": None,
        "arm_unreadable_s": None,
        "recovered_s": 0.0,  # nothing was interrupted
        "arm_rest_s": None,
        "palm_off_s": None,
    }
    assert _arm({**row, "target": "video"}) == "kept following the jog"
    assert _arm({**row, "target": "netsim", "recovered_s": 0.3}).startswith("slowed")


def test_a_link_simulator_back_before_a_lift_could_complete_needs_no_palm_off():
    from harness.faults.matrix import STALE_AFTER_S, back_before_a_lift_could_show
    from operator_side.node.config import OperatorLinkConfig

    assert OperatorLinkConfig().stale_after_ms / 1000 == STALE_AFTER_S  # one limit, not two
    assert back_before_a_lift_could_show(0.18)  # the loaded CI run: stale for 30 ms
    assert not back_before_a_lift_could_show(0.3)  # stale long enough to be off: judged
    assert not back_before_a_lift_could_show(None)  # not netsim's cell, or never back


def test_nothing_breaking_is_not_a_link_back_at_once_for_netsims_own_cells():
    from harness.faults.matrix import CellResult

    row = CellResult(
        "netsim", "restart", "a human (restart)", 0.02, None, None, None, None, None, None,
        recovered_s=0.0, gripper_held=True, gripper_min_pos=204.0, released_still_s=0.25,
        released_silence_s=0.01,
        recording_ok=True, recording_gap_s=0.003, recording_records=589, notes="",
        link_back_s=0.6,
    )  # fmt: skip
    assert row.whole_again_s == 0.6
    # the arm never stopped although the link was away 0.6 s: no excuse, a failure
    assert not back_before_a_stop_was_due(row.arm_still_s, row.whole_again_s, row.arm_rest_s)
