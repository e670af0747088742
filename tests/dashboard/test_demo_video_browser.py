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
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from headless_chromium import Chromium, needs_chromium

pytest.importorskip("aiortc", reason="the demo's video needs the 'video' extra")

from common.transport import free_loopback_ports

pytestmark = [pytest.mark.slow, pytest.mark.timeout(150), needs_chromium]


def test_the_demo_page_plays_the_robots_video_offered_through_the_link():
    port = free_loopback_ports(1)[0]
    argv = [sys.executable, "-m", "deploy.cli", "demo", "--dashboard", "--json"]
    argv += ["--duration", "120", "--set", f"operator.dashboard.port={port}"]
    demo = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        for line in demo.stderr:  # the demo names its dashboard once the robot answered
            if "dashboard http" in line or time.monotonic() > deadline:
                break
        with Chromium(width=1280, height=900) as browser:
            browser.navigate(f"http://127.0.0.1:{port}/")
            browser.wait_until(
                "dxp.video ? dxp.video.latencies.length : 0",
                lambda n: n >= 30,
                timeout_s=60,
                poll_s=0.5,
            )
            summary = browser.evaluate("dxp.video.summary()")
            errors = browser.page_errors()
        time.sleep(1.0)  # the tab is gone: the page's bye (or the dead peer) closes the camera
        demo.send_signal(signal.SIGINT)  # Ctrl-C, as a user ends it
        stdout, stderr = demo.communicate(timeout=60)
    finally:
        if demo.poll() is None:
            demo.kill()
            demo.wait()
    assert errors == [], errors
    assert summary["unreadable"] == 0, summary  # the stamped frames decoded in the page
    assert demo.returncode == 0, stderr[-3000:]
    out = json.loads(stdout)
    assert out["errors"] == []
    logs = Path(out["logs"])
    video_log = (logs / "video.log").read_text()
    assert "opened for a viewer" in video_log
    robot = json.loads((logs / "robot-stats.json").read_text())
    # the offer crossed the link to the robot node, which carried it to the video server
    assert robot.get("video_offers") == 1 and robot.get("video_answers_sent") == 1, robot
