"""``deepxpalm demo --dashboard`` in headless chromium: the page's own video code, over the link.

The demo sets the dashboard's ``video_url = "link"``: the page's offer goes
to the dashboard, crosses the link simulator inside a ``VSIG`` message to
the robot node, which hands it to the video server on its loopback. This
runs the page's JavaScript (video.js) in a real browser against that path,
as a user opening the demo's address would, where the other video tests
speak the page's protocol from aiortc.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest
from headless_chromium import Chromium, needs_chromium, play_video
from tests_support import DashboardDemo

pytest.importorskip("aiortc", reason="the demo's video needs the 'video' extra")

pytestmark = [pytest.mark.slow, pytest.mark.timeout(150), needs_chromium]


def test_the_demo_page_plays_the_robots_video_offered_through_the_link():
    with DashboardDemo(ready_timeout_s=60) as demo:
        with Chromium(width=1280, height=900) as browser:
            summary, errors = play_video(browser, demo.url, frames=30)
        time.sleep(1.0)  # the tab is gone: the page's bye (or the dead peer) closes the camera
        code, out, stderr = demo.finish()
    assert errors == [], errors
    assert summary["unreadable"] == 0, summary  # the stamped frames decoded in the page
    assert code == 0, stderr[-3000:]
    assert out["errors"] == []
    logs = Path(out["logs"])
    video_log = (logs / "video.log").read_text()
    assert "opened for a viewer" in video_log
    robot = json.loads((logs / "robot-stats.json").read_text())
    # the offer crossed the link to the robot node, which carried it to the video server
    assert robot.get("video_offers") == 1 and robot.get("video_answers_sent") == 1, robot
