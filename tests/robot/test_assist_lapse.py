"""An assist whose enable lapses mid re-grasp, then is held again: it closes before it judges.

On a lossy link the operator withholds the enable while its telemetry is
stale, and a gap past the jog deadman ends the assist. If that happens while
the fingers are eased off the pipette, the next hold finds nothing to feel;
the task table's one bad_day failure was that (the palm empty, eight hand
grasps after it). The state machine is driven step by step here, with the
node's parts replaced by what it reads and the commands it hands on.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from common.tactile.contract import pattern_of
from common.tactile.synthetic import SyntheticTactileModel
from robot_side.arm.base import TELEMETRY_POSE_KEYS, ArmLimits
from robot_side.node.assist import Assist
from robot_side.node.config import AssistConfig

MS = 1_000_000
LEFT = pattern_of(2, 1)  # 90 deg, left: a shift


class Desk:
    """The command desk as the assist sees it: the latch, the grip level, the holder's path."""

    def __init__(self) -> None:
        self.stop_latch = SimpleNamespace(latched=False)
        self.grip_level_commanded = 16
        self.sent: list[str] = []

    def act_for_holder(self, cmd, enable_ns) -> bool:
        self.sent.append(cmd.action)
        return True


def _rig():
    rng = np.random.default_rng(3)
    model = SyntheticTactileModel(seed=1)
    frame = model.grasp_frame(model.draw_grasp(LEFT, rng), 16, rng)
    pipeline = SimpleNamespace(
        render=SimpleNamespace(mode="mask"),
        last_stimulus=SimpleNamespace(contact=True, pattern=LEFT),
        last_capture_ns=0,
        last_frame=frame,
    )
    pose = dict(zip(TELEMETRY_POSE_KEYS, (-0.3, -0.13, 0.12, 0.0, 3.14, 0.0), strict=True))
    workers = SimpleNamespace(workers={"arm": 1, "gripper": 1}, arm_readings=lambda: pose)
    clock = [10_000 * MS]
    desk = Desk()
    assist = Assist(
        AssistConfig(),
        pipeline,
        workers,
        act=desk.act_for_holder,
        stop_latched=lambda: desk.stop_latch.latched,
        grip_level=lambda: desk.grip_level_commanded,
        limits=ArmLimits(),
        now=lambda: clock[0],
        recorder=None,
        announce=lambda: None,
    )
    return assist, desk, pipeline, clock


def _run(assist, clock, ms: int, enable_every_ms: int | None = None) -> None:
    for _ in range(ms // 5):
        clock[0] += 5 * MS
        assist.pipeline.last_capture_ns = clock[0]  # frames keep coming at the node's rate
        if enable_every_ms and (clock[0] // MS) % enable_every_ms == 0:
            assist.hold(clock[0], clock[0])
        assist.step(clock[0])


def test_a_hold_after_a_lapse_with_the_fingers_eased_closes_them_first():
    assist, desk, pipeline, clock = _rig()
    assist.hold(clock[0], clock[0])
    _run(assist, clock, 20, enable_every_ms=50)
    assert assist.phase == "release" and desk.sent == ["gripper_ease"]
    pipeline.last_stimulus = SimpleNamespace(contact=False, pattern=None)  # the pads let go
    _run(assist, clock, 100, enable_every_ms=50)
    assert assist.phase == "shift"
    _run(assist, clock, 400)  # the enable stops coming: its deadman ends the assist
    assert assist.phase == "off" and "arm_jog_end" in desk.sent
    assert desk.sent.count("gripper_close") == 0  # the fingers stay where the lapse left them
    assist.hold(clock[0], clock[0])  # held again: nothing to feel, the fingers eased
    _run(assist, clock, 20, enable_every_ms=50)
    assert desk.sent[-1] == "gripper_close", desk.sent
    assert assist.phase == "close", assist.why


def test_the_holders_own_gripper_command_leaves_the_fingers_to_the_holder():
    assist, desk, pipeline, clock = _rig()
    assist.hold(clock[0], clock[0])
    _run(assist, clock, 20, enable_every_ms=50)
    pipeline.last_stimulus = SimpleNamespace(contact=False, pattern=None)
    _run(assist, clock, 400)
    assert assist.phase == "off"
    assist.end("the holder's own gripper_open")
    assist.gripper_taken()  # what the desk does on the holder's gripper command
    assist.hold(clock[0], clock[0])
    _run(assist, clock, 20, enable_every_ms=50)
    assert "gripper_close" not in desk.sent and assist.phase == "waiting"
