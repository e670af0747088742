"""The video server records its camera into an MCAP beside the robot's, on the robot's clock.

The test pattern stamps its capture time into each picture, so the file is
checked from what a reader of it sees: each recorded JPEG decodes to the
picture taken at the recorded time, at about ``record_fps``, without anyone
watching the stream.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

pytest.importorskip("aiortc", reason="the video server needs the 'video' extra")

from common.recording.mcap_recorder import read_metadata, read_recording
from robot_side.camera.config import TestPatternConfig
from robot_side.camera.stamp import MS_MODULO, read_stamp
from robot_side.video.camera_recording import CHANNEL, decode_jpeg
from robot_side.video.server import VideoConfig, VideoServer, build_source


def test_recording_holds_the_frames_taken_at_their_recorded_times(tmp_path):
    path = tmp_path / "camera.mcap"
    pattern = TestPatternConfig(width=320, height=240, fps=30)
    config = VideoConfig(port=0, test_pattern=pattern, record=path, record_fps=10)
    source = build_source(config)
    t_start = time.monotonic_ns()
    with VideoServer(source, config):
        time.sleep(2.0)
    t_end = time.monotonic_ns()
    records = [(t, r) for ch, t, r in read_recording(path) if ch == CHANNEL]
    meta = read_metadata(path)
    assert meta["deepxpalm.camera"]["camera"] == "test_pattern"
    assert meta["deepxpalm.node"]["node"] == "video"
    # nobody watched: the recording alone opened the camera, and it is closed again
    assert source.opened == 1 and not source.is_connected
    times = np.array([t for t, _ in records])
    assert all(t_start < t < t_end for t in times)  # the monotonic clock, as robot.mcap's
    # 10 fps for 2 s: about 20 (fewer on a starved machine, never more than the rate allows)
    assert 8 <= len(records) <= 21, len(records)
    # on average never faster than record_fps (a late frame may be followed by an early one:
    # frames keep to the 100 ms grid rather than drifting)
    assert (times[-1] - times[0]) / (len(times) - 1) >= 0.095e9, np.diff(times)
    wall_offset = int(meta["deepxpalm.clock"]["wall_offset_ns"])
    for t, r in records:
        assert r["t_capture_ns"] == t and r["format"] == "jpeg"
        rgb = decode_jpeg(r["data"])
        assert rgb.shape == (240, 320, 3) == (r["height"], r["width"], 3)
        stamp = read_stamp(rgb)
        assert stamp is not None, "the picture does not survive JPEG"
        # the stamp is the wall clock at capture; the record's time is that moment on the
        # monotonic clock (the two clocks' offset, measured when the file opened, within 2 ms)
        assert abs(stamp[0] - (t + wall_offset) // 1_000_000 % MS_MODULO) <= 2
