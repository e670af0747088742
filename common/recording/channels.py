"""What the nodes record, and the interface a recorder implements.

Both nodes call ``recorder.write(channel, t_ns, record)`` at the points
listed in ``CHANNELS`` with a plain dict (numbers, strings, lists, bytes,
NumPy arrays); a recorder turns that into a log file. ``NullRecorder`` is
what a node uses when recording is off, so the hot path pays one call.
"""

from __future__ import annotations

from typing import Any, Protocol

from common.tactile.contract import FRAME_SHAPE

#: channel -> what it holds (the MCAP recorder uses these as topics)
CHANNELS: dict[str, str] = {
    "robot/frame": f"tactile frame as processed: frame {FRAME_SHAPE} N, frame_seq, t_capture_ns",
    "robot/prediction": "classifier output: angle/position probabilities, pattern, confidence",
    "robot/stimulus": "stimulus sent: the wire bytes (topic + msgpack) and seq",
    "robot/command": "operator command received and what was done with it: outcome, the "
    "velocity the arm was sent (sent_velocity) and the operator's send time (t_sent_ns)",
    "robot/link": "robot link state and counters, at the heartbeat rate",
    "robot/arm": "arm state at the heartbeat rate: tcp_pose (6) m and rad, joints (6) rad",
    "robot/gripper": "gripper state at the heartbeat rate: position (0..255), object_status",
    "operator/stimulus": "stimulus received: the wire bytes and local receive time",
    "operator/servo_goals": "servo goal counts written (ids 1..6) and their angles",
    "operator/command": "command sent to the robot: the wire bytes",
    "operator/link": "operator link state, age, clock offset and counters",
    "operator/episode_mark": "the operator's mark on the episode in progress (dashboard): kind "
    "failed, discard or success, the optional task string, and where it came from (source)",
    "camera/image": "a camera picture (video server, camera.mcap): JPEG bytes in data, "
    "t_capture_ns on the robot's monotonic clock, capture_wall_ns, width, height",
}


class Recorder(Protocol):
    def write(self, channel: str, t_ns: int, record: dict[str, Any]) -> None: ...

    def close(self) -> None: ...


class NullRecorder:
    """Recording off."""

    def write(self, channel: str, t_ns: int, record: dict[str, Any]) -> None:
        return None

    def close(self) -> None:
        return None
