"""Video through a TURN server: the page in headless chromium, told to use relays only.

Sites that cannot reach each other over UDP need a TURN server both reach
(docs/dashboard.md, Video). This runs coturn on loopback with a user and a
password, gives both ends the same ``ice`` settings (the password from a
file, as on a real install) and sets the page's ``transport_policy =
"relay"``, so a frame that arrives has crossed the TURN server. The pair
the browser selected is read from its own WebRTC statistics, and coturn's
log shows the allocation.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import time

import pytest
from headless_chromium import MISSED_STAMPS_ALLOWED, Chromium, needs_chromium, play_video

pytest.importorskip("aiortc")

from common.wire.ice import IceConfig
from common.wire.transport import free_loopback_ports

TURNSERVER = shutil.which("turnserver")

pytestmark = [
    pytest.mark.slow,
    pytest.mark.timeout(120),
    needs_chromium,
    pytest.mark.skipif(
        TURNSERVER is None and not os.environ.get("CI"),
        reason="coturn is not installed: run scripts/install-test-system-packages.sh "
        "(required in CI)",
    ),
]


@pytest.fixture
def turn_server(tmp_path):
    """coturn on 127.0.0.1 with one long-term user; (ice settings, its log file)."""
    port, low = free_loopback_ports(2)
    log_file = tmp_path / "turnserver.log"
    password = tmp_path / "turn.password"
    password.write_text("pipette-42\n")
    password.chmod(0o600)
    argv = [TURNSERVER or "turnserver", "-n", "--no-cli", "--no-tls", "--no-dtls"]
    argv += ["--listening-ip", "127.0.0.1", "--relay-ip", "127.0.0.1"]
    argv += ["--listening-port", str(port), "--allow-loopback-peers"]
    argv += ["--min-port", str(low), "--max-port", str(low + 20)]
    argv += ["--lt-cred-mech", "--user", "dxp:pipette-42", "--realm", "deepxpalm.test"]
    argv += ["--log-file", str(log_file), "--simple-log", "--verbose", "--no-stdout-log"]
    argv += ["--pidfile", str(tmp_path / "turnserver.pid")]
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
    deadline = time.monotonic() + 10
    while "listener opened" not in (log_file.read_text() if log_file.exists() else ""):
        assert proc.poll() is None, f"turnserver exited with {proc.returncode}"
        assert time.monotonic() < deadline, "turnserver did not open its listener"
        time.sleep(0.05)
    ice = dict(servers=(f"turn:127.0.0.1:{port}",), username="dxp", credential_file=password)
    yield ice, log_file
    proc.terminate()
    proc.wait(10)


def test_the_page_gets_the_robots_video_through_turn_only(turn_server):
    from operator_side.dashboard import Dashboard, DashboardConfig
    from operator_side.node import OperatorNode
    from operator_side.node.config import OperatorConfig
    from operator_side.servos.in_memory import InMemoryServoBus
    from robot_side.camera.config import TestPatternConfig
    from robot_side.camera.test_pattern import TestPatternCamera
    from robot_side.video.server import VideoConfig, VideoServer

    ice, turn_log = turn_server
    source = TestPatternCamera(TestPatternConfig(width=320, height=240, fps=15))
    node = OperatorNode(OperatorConfig(), InMemoryServoBus())  # the page needs a node; idle
    with VideoServer(source, VideoConfig(port=0, ice=IceConfig(**ice))) as server:
        page_ice = IceConfig(**ice, transport_policy="relay")
        dashboard = Dashboard(node, DashboardConfig(port=0, video_url=server.url, ice=page_ice))
        dashboard.start()
        try:
            with Chromium(width=1280, height=900) as browser:
                summary, errors = play_video(browser, dashboard.url, frames=20)
                path = browser.evaluate("dxp.video.path()")
        finally:
            dashboard.stop()
    assert errors == [], errors
    assert summary["unreadable"] <= MISSED_STAMPS_ALLOWED, summary
    assert path is not None and path["local"] == "relay", f"the browser's pair: {path}"
    log = turn_log.read_text()
    assert "ALLOCATE processed, success" in log, log[-3000:]
    assert source.opened == 1
