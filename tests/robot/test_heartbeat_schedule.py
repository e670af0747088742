"""The robot's heartbeats: the grid's exact rate, and on the fabric no two closer than the
router's rate gate lets through (the newer of two closer ones, which announces a change, was
dropped there)."""

from __future__ import annotations

import itertools
import random

from common.clocks.clock import now_ns
from common.fabric.link import HEARTBEAT_SPACING_MS
from robot_side.node.config import RobotLinkConfig
from robot_side.node.telemetry import HeartbeatSchedule
from router_side.acl import RateLimits

MS = 1_000_000


def test_the_spacing_is_twice_the_routers_heartbeat_gate():
    gate_ms = 1000 / RateLimits().robot_heartbeat_hz
    assert 2 * gate_ms <= HEARTBEAT_SPACING_MS


def test_on_the_fabric_an_announcement_right_after_a_heartbeat_waits_for_the_spacing():
    schedule = HeartbeatSchedule.of_link(RobotLinkConfig(mode="fabric"))
    schedule.sent(100 * MS, on_grid=True)
    assert not schedule.may_announce(102 * MS)
    assert schedule.wake_ns(announce=True) == round((100 + HEARTBEAT_SPACING_MS) * MS)
    assert schedule.may_announce(round((100 + HEARTBEAT_SPACING_MS) * MS))


def test_on_the_fabric_the_grids_heartbeat_right_after_an_announcement_waits_too():
    link = RobotLinkConfig(mode="fabric", heartbeat_early_ms=0.0)
    schedule = HeartbeatSchedule.of_link(link)
    t0 = now_ns()  # the grid starts at the schedule's making
    schedule.sent(t0, on_grid=True)
    schedule.sent(t0 + 48 * MS, on_grid=False)  # an announcement, 2 ms before the grid's next
    assert not schedule.due(t0 + 50 * MS)
    assert schedule.deadline_ns == t0 + round((48 + HEARTBEAT_SPACING_MS) * MS)
    assert schedule.due(schedule.deadline_ns)


def test_on_a_direct_link_an_announcement_goes_at_once():
    schedule = HeartbeatSchedule.of_link(RobotLinkConfig(mode="bind"))
    schedule.sent(100 * MS, on_grid=True)
    assert schedule.may_announce(100 * MS)
    assert schedule.wake_ns(announce=True) <= 100 * MS


def test_announcements_keep_the_grids_rate_and_no_two_heartbeats_come_closer_than_the_spacing():
    """A loop that wakes when the schedule says (or at a random frame), for 60 s, with an
    announcement wanted at random moments: the grid's rate holds, every heartbeat is at least
    the spacing from the last, and none is further than a period plus the spacing."""
    link = RobotLinkConfig(mode="fabric")
    schedule = HeartbeatSchedule.of_link(link)
    rng = random.Random(0)
    period = round(1e9 / link.heartbeat_rate_hz)
    spacing = round(HEARTBEAT_SPACING_MS * MS)
    now = now_ns()  # the grid starts at the schedule's making
    end, wanted = now + 60 * 10**9, False
    sent: list[int] = []
    grid = 0
    while now < end:
        if rng.random() < 0.02:
            wanted = True
        on_grid = schedule.due(now)
        if on_grid or (wanted and schedule.may_announce(now)):
            schedule.sent(now, on_grid)
            sent.append(now)
            grid += on_grid
            wanted = False
        frame = now + rng.randint(1 * MS, 9 * MS)  # the next frame wakes the loop
        now = max(now + 1, min(frame, schedule.wake_ns(wanted)))
    gaps = [b - a for a, b in itertools.pairwise(sent)]
    assert min(gaps) >= spacing
    assert max(gaps) <= period + spacing
    assert abs(grid - link.heartbeat_rate_hz * 60) <= 1, grid
    assert len(sent) > grid  # the announcements went out beside the grid
