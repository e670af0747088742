"""When a fault cell may excuse a missing stop: the link came back before one could show."""

from __future__ import annotations

from deploy.faults.matrix import ARM_STILL_BUDGET_S, STILL_FOR_S, back_before_a_stop_was_due


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
    from deploy.bench.faults import _arm

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
