"""``deepxpalm robot``: run the robot node on the robot PC."""

from __future__ import annotations

import argparse
from typing import Any

from common.process.command_line import add_config_arguments, run_node
from robot_side.node.config import RobotConfig


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_config_arguments(parser, RobotConfig, "robot", example="render.mode=direct", record=True)


def _build(config: RobotConfig, recorder: Any) -> Any:
    from robot_side.node import build_robot_node  # not for --help: it loads the devices
    from robot_side.node.link_setup import check_command_access

    check_command_access(config)  # before any device is opened
    node = build_robot_node(config, recorder=recorder)
    if recorder is not None:  # arm and gripper state at each heartbeat, for datasets
        from robot_side.devices.device_state_recorder import DeviceStateRecorder

        node.recorder = DeviceStateRecorder(recorder, node.arm, node.gripper)
    return node


def run(args: argparse.Namespace) -> int:
    return run_node(args, RobotConfig, "robot", _build)
