"""Keyframes: the held stimulus sent again, filling the gaps between heartbeats on the fabric.

A heartbeat confirms the current stimulus as a keyframe does. Where keyframes
come more often than heartbeats (the fabric: 25 ms against 50), a keyframe is
due an interval after the last stimulus or heartbeat: the operator hears the
held grasp confirmed every 25 ms with a third fewer datagrams than both at
their own rates. On a direct link (500 ms against 50) heartbeats change nothing.
"""

from __future__ import annotations

import numpy as np
import pytest

from common.clocks.clock import VirtualClock
from common.wire.transport import CaptureLink
from robot_side.node import RobotNode
from robot_side.node.config import RobotConfig
from robot_side.node.frame_pipeline import FABRIC_KEYFRAME_MS
from robot_side.tactile.base import GraspTruth, TactileSample

FRAME_NS = round(1e9 / 120)
HEARTBEAT_NS = 50_000_000


def _held_grasp(
    keyframe_ms: float | None,
) -> tuple[VirtualClock, CaptureLink, RobotNode, np.ndarray]:
    """A robot node on a capture link, and a frame pressed the same every time."""
    config = RobotConfig()
    config.render.keyframe_interval_ms = keyframe_ms
    config.render.mode = "direct"
    clock, link = VirtualClock(), CaptureLink()
    node = RobotNode(config, None, now=clock, link=link)
    frame = np.zeros((2, 10, 10), np.float32)
    frame[:, 4:6, 4:6] = 1.0
    return clock, link, node, frame


def _keyframes_in_a_second(keyframe_ms: float | None, heartbeats: bool) -> list[int]:
    """Send times (ns) of the keyframes of one held grasp over a second, heartbeats or not;
    ``keyframe_ms`` None: a direct link's default interval."""
    clock, link, node, frame = _held_grasp(keyframe_ms)
    next_heartbeat = HEARTBEAT_NS
    for seq in range(1, 121):
        clock.advance(FRAME_NS)
        if heartbeats and clock() >= next_heartbeat:
            node.pipeline.heartbeat_sent(clock())
            next_heartbeat += HEARTBEAT_NS
        truth = GraspTruth(pattern=None, grip_level=None)
        sample = TactileSample(frame=frame, seq=seq, t_capture_ns=clock(), truth=truth)
        node.pipeline.offer(sample, clock())
    return [m.t_send_ns for m in link.messages if getattr(m, "keyframe", False)]


def test_on_the_fabric_keyframes_fill_between_heartbeats():
    alone = _keyframes_in_a_second(FABRIC_KEYFRAME_MS, heartbeats=False)
    between = _keyframes_in_a_second(FABRIC_KEYFRAME_MS, heartbeats=True)
    # every 25 ms (a rendered frame later at most) without heartbeats; one between two with them
    assert 25 <= len(alone) <= 40, len(alone)
    assert 15 <= len(between) <= 20, len(between)
    # never longer than a heartbeat period and a frame without the stimulus itself
    gaps = np.diff(between)
    assert gaps.max() <= HEARTBEAT_NS + FRAME_NS, gaps.max()


@pytest.mark.parametrize("heartbeats", [False, True])
def test_on_a_direct_link_heartbeats_leave_the_keyframes_alone(heartbeats: bool):
    sent = _keyframes_in_a_second(None, heartbeats=heartbeats)
    assert len(sent) == 1, sent  # one 500 ms after the grasp's first stimulus


def test_a_heartbeat_names_the_change_the_keyframes_repeat():
    """An operator that lost keyframes still has the change they repeat: the heartbeat names
    that change (its ``stimulus_seq``), so it confirms the palm's stimulus all the same."""
    from common.wire.messages import Heartbeat, Stimulus

    clock, link, node, frame = _held_grasp(FABRIC_KEYFRAME_MS)
    truth = GraspTruth(pattern=None, grip_level=None)
    for seq in range(1, 13):  # 100 ms of a held grasp: its change, then keyframes
        clock.advance(FRAME_NS)
        node.pipeline.offer(TactileSample(frame, seq, clock(), truth), clock())
    node._send_heartbeat()
    stimuli = [m for m in link.messages if isinstance(m, Stimulus)]
    heartbeat = [m for m in link.messages if isinstance(m, Heartbeat)][-1]
    changes = [m.seq for m in stimuli if not m.keyframe]
    assert len(changes) == 1 and stimuli[-1].keyframe, [(m.seq, m.keyframe) for m in stimuli]
    assert heartbeat.stimulus_seq == changes[0] != stimuli[-1].seq
