"""The node's parts as the live views show them: a ``Snapshot`` taken under the arrivals' lock."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from operator_side.dashboard.snapshot import Snapshot

if TYPE_CHECKING:
    from operator_side.node.arrivals import Arrivals
    from operator_side.node.palm import Palm


def take_snapshot(
    arrivals: Arrivals,
    palm: Palm,
    now: int,
    stats: dict[str, float],
    control: dict[str, Any] | None,
) -> Snapshot:
    """The node's parts as the live views show them: copies, taken under the arrivals' lock."""
    stim, frame, robot_stats = arrivals.views()
    _, age = palm.fresh_stimulus(now)
    written = palm.goal_counts()
    return Snapshot(
        link_state=palm.link_state,
        stimulus=None if stim is None else stim.stimulus.copy(),
        pattern=None if stim is None else stim.pattern,
        confidence=None if stim is None else stim.confidence,
        grip_level=None if stim is None else stim.grip_level,
        frame=None if frame is None else frame.frame.copy(),
        goal_counts=written,
        goal_angles=palm.calibration.counts_to_angles(written),
        age_ms=age,
        stats=stats,
        robot_stats=robot_stats,
        control=control,
    )
