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
import os
import signal
import time
from ipaddress import ip_address
from pathlib import Path

import pytest
from headless_chromium import MISSED_STAMPS_ALLOWED, Chromium, needs_chromium, play_video
from tests_support import DashboardDemo, child_processes, listening_sockets

from harness.processes import idle_share, machine_cpu
from robot_side.camera.stamp import MS_MODULO
from robot_side.video.link_signalling import SERVER_WAIT_S

pytest.importorskip("aiortc", reason="the demo's video needs the 'video' extra")

#: serial: a killed video server's replacement needs about a second of CPU to start, and beside
#: another test's deployment a 2-core machine had 1 % to give it (the pages came back in 5.03 s)
pytestmark = [pytest.mark.slow, pytest.mark.timeout(240), needs_chromium, pytest.mark.serial]

#: both pages play again within this of kill -9 of the video server where the machine has CPU
#: to spare (docs/dashboard.md): the unit's 0.2 s RestartSec, the server's start (about a
#: second of CPU), then the offers the robot node held meanwhile are answered at once, and a
#: session's ICE, DTLS and first frame
RECOVER_S = 5.0
#: ... and whatever the load, by the product's own windows: a page offers again 0.25 s after
#: the close (video.js), its offer waits in the robot node for the new server up to
#: SERVER_WAIT_S and is answered at once; then ICE, DTLS and the first frame
OFFER_AGAIN_S = 0.25
SESSION_START_S = 2.0
#: below this share of the machine idle, the server (Nice=0, below the nodes and the tests of
#: the lane beside it) gets too little of it for RECOVER_S, by the unit's design
SPARE_CPU = 0.05


def test_the_demo_page_plays_the_robots_video_offered_through_the_link():
    with DashboardDemo(ready_timeout_s=60) as demo:
        with Chromium(width=1280, height=900) as browser:
            summary, errors = play_video(browser, demo.url, frames=30)
            # a viewer is connected: what the page's process (the demo's operator node) and
            # the video server listen on
            children = child_processes(demo.proc.pid)
            pids = {"page": children["operator"], "video": children["video"]}
            sockets = {role: listening_sockets(pid) for role, pid in pids.items()}
        time.sleep(1.0)  # the tab is gone: the page's bye (or the dead peer) closes the camera
        code, out, stderr = demo.finish()
    assert errors == [], errors
    # the stamped frames decoded in the page, but for the instrument's one miss (headless_chromium)
    assert summary["unreadable"] <= MISSED_STAMPS_ALLOWED, summary
    # nothing listens beyond loopback (the demo's interfaces): not the page, not the media,
    # not an mDNS listener on 0.0.0.0:5353
    outside = [s for socks in sockets.values() for s in socks if not ip_address(s[1]).is_loopback]
    assert outside == [], sockets
    assert any(proto.startswith("udp") for proto, _, _ in sockets["video"]), sockets  # media
    assert any(proto.startswith("tcp") for proto, _, _ in sockets["page"]), sockets
    assert code == 0, stderr[-3000:]
    assert out["errors"] == []
    logs = Path(out["logs"])
    video_log = (logs / "video.log").read_text()
    assert "opened for a viewer" in video_log
    robot = json.loads((logs / "robot-stats.json").read_text())
    # the offer crossed the link to the robot node, which carried it to the video server
    assert robot.get("video_offers") == 1 and robot.get("video_answers_sent") == 1, robot


def _stamp_after(browser, since_ms: int) -> bool:
    """The page presented a stamped frame captured after ``since_ms`` (wall clock)."""
    stamp = browser.evaluate("dxp.video ? dxp.video.lastStamp : null")
    return stamp is not None and (stamp - since_ms) % MS_MODULO < MS_MODULO // 2


def test_two_pages_play_and_play_again_after_kill_9_of_the_video_server():
    """Two tabs on the demo (the server used to die of SIGSEGV a second after the second
    viewer); then kill -9 of the video server: the demo and the robot node run on, stimuli
    keep coming, the demo restarts the server and both pages play again within 5 s."""
    with DashboardDemo(ready_timeout_s=90) as demo:
        with Chromium(width=1280, height=900) as a, Chromium(width=1280, height=900) as b:
            for page in (a, b):
                page.navigate(demo.url)
            for page in (a, b):
                page.wait_until(
                    "dxp.video ? dxp.video.latencies.length : 0", lambda n: n >= 30, timeout_s=60
                )
            before = child_processes(demo.proc.pid)
            assert {"robot", "video"} <= set(before), before
            stimuli = a.evaluate("dxp.state.stats.stimuli_received")
            cpu0 = machine_cpu()
            killed_ms = time.time_ns() // 1_000_000
            os.kill(before["video"], signal.SIGKILL)
            t_kill = time.monotonic()
            back: dict[str, float] = {}
            restarted = None  # when the demo's new video server process was there
            while len(back) < 2 and time.monotonic() - t_kill < 30:
                if restarted is None and child_processes(demo.proc.pid).get("video") not in (
                    None,
                    before["video"],
                ):
                    restarted = time.monotonic() - t_kill
                for name, page in (("a", a), ("b", b)):
                    if name not in back and _stamp_after(page, killed_ms):
                        back[name] = time.monotonic() - t_kill
                time.sleep(0.05)
            idle = idle_share(cpu0, machine_cpu())
            after = child_processes(demo.proc.pid)
            stimuli_after = a.evaluate("dxp.state.stats.stimuli_received")
            link = a.evaluate("dxp.state.link_state")
            pages = [p.evaluate("dxp.video.summary()") for p in (a, b)]
            # when each page's new session was answered, ms after the kill: the rest of its
            # recovery is ICE, DTLS and the first keyframe
            answered = [p.evaluate("dxp.video.answeredAt") - killed_ms for p in (a, b)]
            errors = a.page_errors() + b.page_errors()
        code, out, stderr = demo.finish()
    assert errors == [], errors
    assert code == 0, stderr[-3000:]
    children = out["processes"]["children"]
    # the two pages played together without the server dying (the demo would have restarted it)
    assert children["video"]["exit_codes"] == [-9], children["video"]
    assert after.get("robot") == before["robot"], f"the robot node was restarted: {after}"
    assert children["robot"]["restarts"] == 0 and out["errors"] == [], out["errors"]
    assert stimuli_after > stimuli and link == "ok", (stimuli, stimuli_after, link)
    assert after.get("video") not in (None, before["video"]), after
    assert len(back) == 2, f"a page did not play again within 30 s: {back}, {pages}"
    recovered = max(back.values())
    print(f"pages played again {back} s after kill -9 of the video server, {idle:.0%} idle")
    # the demo restarts the server after 0.2 s (its unit's RestartSec); the pages' offers wait
    # in the robot node until it listens: docs/dashboard.md
    timeline = (
        f"the new video server process there {restarted} s after the kill, the pages' offers "
        f"answered {answered} ms after it; {idle:.0%} of the machine's CPU idle meanwhile): {pages}"
    )
    assert max(answered) / 1000 <= OFFER_AGAIN_S + SERVER_WAIT_S + 0.5, (
        f"product: the pages' new offers were not answered within the robot node's "
        f"{SERVER_WAIT_S:g} s wait for a restarted video server ({timeline}"
    )
    assert recovered - max(answered) / 1000 <= SESSION_START_S, (
        f"product: played again {recovered:.2f} s after the kill, over {SESSION_START_S:g} s "
        f"after the answer ({timeline}"
    )
    if idle < SPARE_CPU and recovered >= RECOVER_S:
        print(f"load: {recovered:.2f} s, over {RECOVER_S:g} s, with {idle:.0%} of the machine idle")
        return
    assert recovered < RECOVER_S, (
        f"product: played again after {back} s, not within {RECOVER_S:g} s ({timeline}"
    )
