"""The memory arm and gripper: the real safety layers over drivers that only remember."""

from __future__ import annotations

import time

import numpy as np
import pytest

from common.devices.lifecycle import build_device
from robot_side.arm import KINDS as ARM_KINDS
from robot_side.arm.base import WorkspaceLimitError
from robot_side.gripper import KINDS as GRIPPER_KINDS


def test_memory_arm_records_the_clipped_jog_and_the_deadman_stop() -> None:
    arm = build_device(
        ARM_KINDS, {"kind": "memory", "limits": {"jog_timeout_s": 0.05}}, "robot.arm"
    )
    with arm:
        sent = arm.jog([1.0, 0, 0, 0, 0, 0])
        assert np.allclose(sent, [arm.limits.max_linear_speed_m_s, 0, 0, 0, 0, 0])
        assert np.allclose(arm.sent_jogs[-1], sent)
        deadline = time.monotonic() + 2
        while not arm.stops and time.monotonic() < deadline:
            time.sleep(0.01)
        assert arm.status()["deadman_stops"] == 1 and arm.stops >= 1


def test_memory_arm_moves_at_once_and_refuses_targets_outside_the_box() -> None:
    arm = build_device(ARM_KINDS, {"kind": "memory"}, "robot.arm")
    with arm:
        arm.move_to([0.1, 0.1, 0.2, 0, 3.14, 0])
        assert np.allclose(arm.tcp_pose()[:3], [0.1, 0.1, 0.2])
        with pytest.raises(WorkspaceLimitError):
            arm.move_to([0.9, 0, 0.2, 0, 3.14, 0])
        assert len(arm.moves) == 1


def test_memory_gripper_activates_and_records_commands() -> None:
    gripper = build_device(GRIPPER_KINDS, {"kind": "memory"}, "robot.gripper")
    with gripper:
        assert gripper.is_active()
        gripper.close_to_level(31)
        position = gripper.levels.position(31)
        assert gripper.commands[-1][0] == position == gripper.position()
        assert gripper.grip_level() == 31
        with pytest.raises(ValueError, match="grip level"):
            gripper.close_to_level(32)
        assert len(gripper.commands) == 1
