"""Child process for the live Foxglove test: writes a session as the robot PC's recorders do.

``robot.mcap`` gets the arm and gripper at the heartbeat's 20 Hz and
``camera.mcap`` the camera's pictures at 10 fps (a real JPEG from the
fixture session), each through its own ``McapRecorder`` (1 s chunks), for
the given number of seconds.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from common.recording.mcap_recorder import McapRecorder, read_recording

FIXTURE = Path(__file__).parent / "fixtures" / "session-v1" / "camera.mcap"


def main() -> None:
    out, seconds = Path(sys.argv[1]), float(sys.argv[2])
    jpeg = next(r for c, _, r in read_recording(FIXTURE) if c == "camera/image")
    robot = McapRecorder(out / "robot.mcap", fsync=False)
    camera = McapRecorder(out / "camera.mcap", fsync=False)
    t0 = time.monotonic_ns()
    tick = 0
    next_t = time.monotonic()
    print("recording", flush=True)
    while time.monotonic_ns() - t0 < seconds * 1e9:
        now = time.monotonic_ns()
        pose = np.array([0.3 + 0.001 * tick, -0.1, 0.2, 0.0, np.pi, 0.0])
        robot.write("robot/arm", now, {"tcp_pose": pose, "joints": np.zeros(6)})
        robot.write("robot/gripper", now, {"position": tick % 256, "object_status": 0})
        if tick % 2 == 0:
            camera.write(
                "camera/image",
                now,
                {**jpeg, "frame_index": tick // 2, "t_capture_ns": now, "camera": "overview"},
            )
        tick += 1
        next_t += 0.05
        time.sleep(max(0.0, next_t - time.monotonic()))
    robot.close()
    camera.close()


if __name__ == "__main__":
    main()
