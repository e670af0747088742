"""A camera recording stops, whatever its encoder is doing: systemd's stop must not hang."""

from __future__ import annotations

import threading
import time

import pytest

pytest.importorskip("av", reason="the camera recording encodes with PyAV ('video' extra)")

from robot_side.camera.test_pattern import TestPatternCamera
from robot_side.video import camera_recording
from robot_side.video.camera_recording import CameraRecording
from robot_side.video.feed import CameraFeed


def test_a_stuck_encoder_with_a_full_queue_does_not_hold_the_stop(tmp_path, monkeypatch):
    stuck = threading.Event()
    release = threading.Event()

    def stuck_jpeg(encoder, frame):  # an encoder that never comes back (until released)
        stuck.set()
        release.wait(30)
        return b""

    monkeypatch.setattr(camera_recording, "_jpeg", stuck_jpeg)
    feed = CameraFeed(TestPatternCamera())
    rec = CameraRecording(feed, tmp_path / "camera.mcap", fps=30, camera="test").start()
    try:
        assert stuck.wait(10), "the encoder never got a frame"
        deadline = time.monotonic() + 10
        while not rec._queue.full() and time.monotonic() < deadline:  # frames pile up
            time.sleep(0.01)
        assert rec._queue.full()
        stopper = threading.Thread(target=rec.stop, kwargs={"timeout_s": 0.5}, daemon=True)
        t0 = time.monotonic()
        stopper.start()
        stopper.join(5)
        assert not stopper.is_alive(), "stop() blocked on the full queue"
        assert time.monotonic() - t0 < 3
        assert rec.frames_dropped >= 1  # the end mark took a queued frame's place
    finally:
        release.set()
        feed.close()
