"""The action rule: applied commands as the arm and gripper applied them, held at the row rate."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from deploy.export.resample import SessionResampler
from robot_side.arm.base import ArmLimits
from robot_side.gripper.base import GripLevels

MS = 1_000_000


def _rows(events, fps=100):
    r = SessionResampler(fps, {}, {"core"})
    frame = {"frame": np.zeros((2, 10, 10), np.float32), "frame_seq": 1, "t_capture_ns": 0}
    out = list(r.feed("robot/frame", 0, frame))
    for channel, t, rec in events:
        out += list(r.feed(channel, t, rec))
    out += list(r.feed("robot/frame", 2000 * MS, frame))
    return {row["t_ns"]: row["action"] for row in out}


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(-2, 2), min_size=6, max_size=6))
def test_a_jog_is_clipped_as_the_arm_clips_it_and_ends_at_the_jog_timeout(v):
    limits = ArmLimits()
    cmd = {"action": "arm_jog", "velocity": v, "outcome": "applied"}
    rows = _rows([("robot/command", 100 * MS, cmd)])
    jog = rows[110 * MS][:6]
    assert np.linalg.norm(jog[:3]) <= limits.max_linear_speed_m_s * (1 + 1e-6)
    assert np.linalg.norm(jog[3:]) <= limits.max_angular_speed_rad_s * (1 + 1e-6)
    assert not rows[90 * MS][:6].any()  # nothing before the command
    timeout_ms = limits.jog_timeout_s * 1000
    assert not rows[round(100 + timeout_ms + 10) * MS][:6].any()  # the deadman stopped it


def test_rejected_commands_change_nothing_and_gripper_targets_follow_levels():
    levels = GripLevels()
    events = [
        (
            "robot/command",
            100 * MS,
            {"action": "gripper_close", "grip_level": 20, "outcome": "applied"},
        ),
        ("robot/command", 300 * MS, {"action": "gripper_open", "outcome": "rejected: fault"}),
        ("robot/command", 500 * MS, {"action": "gripper_open", "outcome": "applied"}),
        (
            "robot/command",
            600 * MS,
            {"action": "arm_jog", "velocity": [0.01, 0, 0, 0, 0, 0], "outcome": "applied"},
        ),
        ("robot/command", 650 * MS, {"action": "arm_stop", "outcome": "applied"}),
    ]
    rows = _rows(events)
    assert rows[50 * MS][6] == 0
    assert rows[200 * MS][6] == levels.position(20)
    assert rows[400 * MS][6] == levels.position(20)  # the rejected open did nothing
    assert rows[550 * MS][6] == 0
    assert rows[620 * MS][0] == np.float32(0.01)
    assert not rows[660 * MS][:6].any()
