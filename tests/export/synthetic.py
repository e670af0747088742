"""A robot recording written the way the robot node writes it, without running the node.

For tests that need a recording of a known shape fast (a damaged file, a
jog on a slow link): frames at 30 Hz, arm and gripper at 20 Hz, one MCAP
chunk per recorded second as the recorder's flush makes them, and the
node's config stored as the node stores it.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from common.recording.mcap_recorder import McapRecorder

MS = 1_000_000
ROBOT_CONFIG = "[robot.arm.limits]\njog_timeout_s = 0.25\n"
POSE = [0.1, 0.0, 0.3, 0.0, 3.14, 0.0]


def robot_recording(
    path: Path,
    seconds: float,
    *,
    t0_ns: int = 10_000 * MS,
    extra: Callable[[McapRecorder, int], None] | None = None,
) -> None:
    """Write ``seconds`` of frames (in contact), arm and gripper records to ``path``.

    ``extra(recorder, t_ns)`` is called every 10 ms of recorded time to add
    what a test needs (commands). Records carry the times given, not the
    wall clock, so the file is the same on a loaded machine.
    """
    metadata = {"deepxpalm.node": {"node": "robot", "config_toml": ROBOT_CONFIG}}
    rng = np.random.default_rng(0)
    with McapRecorder(path, flush_interval_s=3600, fsync=False, metadata=metadata) as rec:
        seq = 0
        for step in range(round(seconds * 100)):  # 10 ms steps
            t = t0_ns + step * 10 * MS
            if step % 3 == 0:
                seq += 1
                frame = rng.uniform(0.5, 1.0, (2, 10, 10)).astype(np.float32)
                rec.write("robot/frame", t, {"frame": frame, "frame_seq": seq, "t_capture_ns": t})
            if step % 5 == 0:
                rec.write("robot/arm", t, {"tcp_pose": np.array(POSE), "joints": np.zeros(6)})
                rec.write("robot/gripper", t, _gripper(t))
                rec.write("robot/link", t, {"state": "ok"})
            if extra is not None:
                extra(rec, t)
            if step % 100 == 99:
                assert rec.flush()


def _gripper(t: int) -> dict[str, Any]:
    return {
        "position": 120.0,
        "requested_position": 120.0,
        "object_status": 2,
        "activation": 3,
        "fault": 0,
    }


def flip(path: Path, at_fraction: float, n: int = 64) -> int:
    """Invert ``n`` bytes at ``at_fraction`` of the file; returns the offset."""
    data = bytearray(path.read_bytes())
    at = int(len(data) * at_fraction)
    data[at : at + n] = bytes(b ^ 0xFF for b in data[at : at + n])
    path.write_bytes(bytes(data))
    return at
