"""A robot node from its config: the devices and the classifier it names, and nothing else."""

from __future__ import annotations

from typing import Any

import zmq

from common.devices.lifecycle import Device, build_device
from common.recording.channels import Recorder
from robot_side.node.config import RobotConfig
from robot_side.node.robot_node import RobotNode


def build_robot_node(
    config: RobotConfig, ctx: zmq.Context | None = None, recorder: Recorder | None = None
) -> RobotNode:
    """Build the devices and classifier a config names (a kind not named is never imported)."""
    from robot_side.arm import KINDS as ARM_KINDS
    from robot_side.gripper import KINDS as GRIPPER_KINDS
    from robot_side.tactile import KINDS as TACTILE_KINDS

    tactile = build_device(TACTILE_KINDS, config.tactile, "robot.tactile")
    gripper = _optional(GRIPPER_KINDS, config.gripper, "robot.gripper")
    arm = _optional(ARM_KINDS, config.arm, "robot.arm")
    classifier = None
    if config.render.mode == "mask":
        from robot_side.perception import load_classifier

        classifier = load_classifier(config.classifier.path, backend=config.classifier.backend)
    return RobotNode(
        config, tactile, classifier=classifier, gripper=gripper, arm=arm, ctx=ctx, recorder=recorder
    )


def _optional(registry: dict[str, str], section: dict[str, Any], where: str) -> Device | None:
    if section.get("kind", "none") == "none":
        return None
    return build_device(registry, section, where)
