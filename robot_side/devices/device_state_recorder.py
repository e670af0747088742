"""Arm and gripper state in a recording, read on the node's own thread.

A dataset made from a session needs where the arm and the fingers were, not
only what the operator asked for. ``DeviceStateRecorder`` wraps the node's
recorder: each time the node writes its heartbeat record (``robot/link``, on
the node's loop thread, 20 Hz) it also reads the arm and the gripper and
writes ``robot/arm`` and ``robot/gripper``. The reads happen on the same
thread that sends the devices their commands, so they never interleave with
a command on the wire. A device that cannot be read (not connected yet,
recovering) is skipped for that beat and counted.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from common.errors import DeviceError
from common.recording.channels import Recorder

log = logging.getLogger(__name__)

HEARTBEAT_CHANNEL = "robot/link"


def record_device_state(recorder: Recorder, t_ns: int, arm: Any, gripper: Any) -> int:
    """Write one ``robot/arm`` and one ``robot/gripper`` record; returns how many were skipped."""
    skipped = 0
    if arm is not None:
        try:
            pose = np.asarray(arm.tcp_pose(), dtype=np.float64)
            joints = np.asarray(arm.joint_positions(), dtype=np.float64)
        except DeviceError as e:
            skipped += 1
            log.debug("arm state not recorded: %s", e)
        else:
            recorder.write("robot/arm", t_ns, {"tcp_pose": pose, "joints": joints})
    if gripper is not None:
        try:
            st = gripper.state()
        except DeviceError as e:
            skipped += 1
            log.debug("gripper state not recorded: %s", e)
        else:
            recorder.write(
                "robot/gripper",
                t_ns,
                {
                    "position": int(st.position),
                    "requested_position": int(st.requested_position),
                    "object_status": int(st.object_status),
                    "activation": int(st.activation),
                    "fault": int(st.fault),
                },
            )
    return skipped


class DeviceStateRecorder:
    """A recorder that adds the arm's and gripper's state to every heartbeat record."""

    def __init__(self, inner: Recorder, arm: Any, gripper: Any) -> None:
        self.inner = inner
        self.arm = arm
        self.gripper = gripper
        self.reads_skipped = 0

    def write(self, channel: str, t_ns: int, record: dict[str, Any]) -> None:
        self.inner.write(channel, t_ns, record)
        if channel == HEARTBEAT_CHANNEL:
            self.reads_skipped += record_device_state(self.inner, t_ns, self.arm, self.gripper)

    def close(self) -> None:
        self.inner.close()

    def __getattr__(self, name: str) -> Any:  # stats(), flush(), add_metadata() of the inner one
        return getattr(self.inner, name)
