"""From an admitted command's action to the device call that carries it out.

One row per device action; the lease actions and ``arm_resume`` move no
device (the command desk and the stop latch use them up).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from common.wire.messages import Command
from robot_side.arm.base import Arm
from robot_side.gripper.base import Gripper

#: ``gripper_close`` without a grip level closes to this one (of 1..31, the middle)
DEFAULT_CLOSE_LEVEL = 16

#: (the call, its arguments)
Call = tuple[Callable[..., Any], tuple[Any, ...]]


@dataclass(frozen=True)
class DeviceCall:
    """Which device an action goes to, and the call it makes there.

    ``make(device, command, sent_ns)``: ``sent_ns`` is the operator's send time
    on our clock (None before the clocks are synced).
    """

    device: str
    make: Callable[[Any, Command, int | None], Call]


def _jog(arm: Arm, cmd: Command, sent_ns: int | None) -> Call:
    if cmd.velocity is None:  # a jog without a velocity is a stop
        return arm.stop, ()
    return arm.jog, (cmd.velocity, None if sent_ns is None else sent_ns / 1e9)


def _stop(arm: Arm, cmd: Command, sent_ns: int | None) -> Call:
    return arm.stop, ()


def _open(gripper: Gripper, cmd: Command, sent_ns: int | None) -> Call:
    return gripper.open, ()


def _close(gripper: Gripper, cmd: Command, sent_ns: int | None) -> Call:
    return gripper.close_to_level, (cmd.grip_level or DEFAULT_CLOSE_LEVEL,)


def _hold(gripper: Gripper, cmd: Command, sent_ns: int | None) -> Call:
    return gripper.hold, ()


def _ease(gripper: Gripper, cmd: Command, sent_ns: int | None) -> Call:
    return gripper.ease, ()


DEVICE_CALLS: dict[str, DeviceCall] = {
    "arm_jog": DeviceCall("arm", _jog),
    "arm_jog_end": DeviceCall("arm", _stop),
    "arm_stop": DeviceCall("arm", _stop),
    "gripper_open": DeviceCall("gripper", _open),
    "gripper_close": DeviceCall("gripper", _close),
    "gripper_hold": DeviceCall("gripper", _hold),
    "gripper_ease": DeviceCall("gripper", _ease),
}
