"""``deepxpalm demo --scene lab --dashboard``: the lab's camera reaches the page.

The whole demo as a user runs it: the world in its own process, the robot
node on it, the link simulator, the video server on the world's overview
camera, and the operator node with its dashboard. The test is the page:
it offers over the dashboard's socket, the offer crosses the link simulator
to the robot and its video server, and the lab's frames come back.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

pytest.importorskip("mujoco", reason="the simulated lab needs the 'lab' extra (MuJoCo)")
pytest.importorskip("aiortc", reason="the demo's video needs the 'video' extra")

from tests_support import DashboardDemo
from video_page import watch_video

pytestmark = [pytest.mark.slow, pytest.mark.timeout(150)]


def test_the_lab_demo_shows_the_lab_camera_through_the_link():
    with DashboardDemo("--scene", "lab") as demo:
        out = asyncio.run(watch_video(demo.ws_url, frames=4))
        assert "closed" not in out, out
        assert out["answer"]["source"] == "lab overview"
        assert (out["answer"]["width"], out["answer"]["height"]) == (320, 240)
        for rgb in out["frames"]:
            assert rgb.shape == (240, 320, 3) and rgb.std() > 5  # the lab, not a blank
        code, summary, stderr = demo.finish()
    assert code == 0, stderr[-3000:]
    assert summary["errors"] == []
    logs = Path(summary["logs"])
    video_log = (logs / "video.log").read_text()
    assert "lab overview opened for a viewer" in video_log
    assert "lab overview closed (no viewers)" in video_log  # the page left: no more renders
    assert (logs / "world.json").exists()  # the world ran as its own process
