"""Deadline helpers: a periodic duty keeps its average rate while riding on other wake-ups."""

from __future__ import annotations

import itertools

import pytest

from common.clocks.clock import Periodic

MS = 1_000_000


def test_a_duty_done_early_keeps_the_average_rate_exact():
    duty = Periodic(20.0, early_s=0.02, start_ns=0)
    done_at = []
    # a loop awake every 16.7 ms (60 Hz frames) does the duty on the first
    # wake-up inside its early window
    for k in range(1, 601):
        now = round(k * 1e9 / 60)
        if duty.due(now):
            done_at.append(now)
            duty.done(now)
    # the first duty ran 16.7 ms after its deadline at 0; the grid did not move
    gaps = [b - a for a, b in itertools.pairwise(done_at[1:])]
    assert len(done_at) == pytest.approx(10 * 20, abs=1)  # 10 s at 20 Hz
    assert max(gaps) <= 50 * MS + 20 * MS
    assert min(gaps) >= 50 * MS - 20 * MS


def test_a_duty_is_not_due_before_its_early_window():
    duty = Periodic(20.0, early_s=0.01, start_ns=100 * MS)
    assert not duty.due(89 * MS)
    assert duty.due(90 * MS)
    duty.done(90 * MS)
    assert duty.deadline_ns == 150 * MS


def test_after_a_stall_the_duty_restarts_instead_of_bursting():
    duty = Periodic(20.0, early_s=0.01, start_ns=0)
    duty.done(0)
    duty.done(1000 * MS)  # a second late
    assert duty.deadline_ns == 1050 * MS
    assert not duty.due(1001 * MS)


@pytest.mark.parametrize("early_s", [-0.001, 0.05, 0.06])
def test_an_early_window_of_a_period_or_more_is_refused(early_s):
    with pytest.raises(ValueError, match="early_s"):
        Periodic(20.0, early_s=early_s)
