"""The video server stops promptly even when a viewer's end of the signalling never answers.

A frozen operator process (SIGSTOP, a hung dashboard loop) keeps its TCP
socket open but never sends the WebSocket close frame; the robot's stop
(systemd's, or the demo's) must not wait websockets' default 10 s for it.
"""

from __future__ import annotations

import socket
import time
from urllib.parse import urlsplit

import pytest

pytest.importorskip("aiortc", reason="the video server needs the 'video' extra")

from robot_side.camera.config import TestPatternConfig
from robot_side.camera.test_pattern import TestPatternCamera
from robot_side.video.server import WS_CLOSE_TIMEOUT_S, VideoConfig, VideoServer

pytestmark = pytest.mark.timeout(60)


def _silent_viewer(url: str) -> socket.socket:
    """A WebSocket opened by hand, then never read from or written to again."""
    parts = urlsplit(url)
    sock = socket.create_connection((parts.hostname, parts.port), timeout=5)
    sock.sendall(
        (
            f"GET /?{parts.query} HTTP/1.1\r\nHost: {parts.netloc}\r\nUpgrade: websocket\r\n"
            "Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
            "Sec-WebSocket-Version: 13\r\n\r\n"
        ).encode()
    )
    reply = sock.recv(4096)
    assert reply.startswith(b"HTTP/1.1 101"), reply[:200]
    return sock


def test_a_viewer_that_never_answers_the_close_does_not_hold_up_the_stop():
    source = TestPatternCamera(TestPatternConfig(width=160, height=120, fps=15))
    server = VideoServer(source, VideoConfig(port=0)).start()
    viewers = [_silent_viewer(server.url) for _ in range(2)]
    try:
        t0 = time.monotonic()
        ended = server.stop(timeout_s=5.0)
        took = time.monotonic() - t0
    finally:
        for v in viewers:
            v.close()
    assert ended, "the video server did not stop within 5 s"
    assert took < WS_CLOSE_TIMEOUT_S + 2.0, f"stop took {took:.1f} s"


@pytest.mark.slow
def test_a_camera_stuck_in_a_capture_does_not_hold_the_stop_past_its_timeout():
    """A camera that stops delivering inside ``capture()`` (a USB camera gone mid-read, a frozen
    lab renderer): the stop still ends within its timeout, which systemd's TimeoutStopSec and
    the SIGTERM test count on; the capture thread is not waited for beyond it."""
    import threading

    stuck = threading.Event()
    release = threading.Event()

    class StuckCamera(TestPatternCamera):
        def capture(self):
            frame = super().capture()
            if self._count >= 3:  # a few frames, then the device stops answering
                stuck.set()
                release.wait(30.0)
            return frame

    camera = StuckCamera(TestPatternConfig(width=160, height=120, fps=15))
    server = VideoServer(camera, VideoConfig(port=0)).start()
    try:
        server.feed.subscribe("viewer")  # as a viewer's first frame does: the camera opens
        assert stuck.wait(10.0), "the camera never got stuck"
        t0 = time.monotonic()
        server.stop(timeout_s=1.0)
        took = time.monotonic() - t0
    finally:
        release.set()
    assert took < 1.5, f"stop took {took:.1f} s with a timeout of 1 s"


def test_a_main_thread_kept_from_running_ends_the_server_with_every_threads_stack():
    """``deepxpalm video`` waits for its stop awake: a main thread that cannot run (native code
    holding the GIL; here a regular expression that backtracks for a minute) ends the process
    within the stall bound, the stuck thread's stack in its log, where systemd's SIGKILL would
    have said nothing. A server that runs normally wakes, re-arms and returns on its stop."""
    import faulthandler
    import subprocess
    import sys
    import threading

    from robot_side.video import cli

    stop = threading.Event()
    threading.Timer(0.3, stop.set).start()
    t0 = time.monotonic()
    cli.wait_for_stop(stop, None)
    cli.wait_for_stop(threading.Event(), 0.2)  # or at the end of its duration
    assert time.monotonic() - t0 < 2.0
    faulthandler.cancel_dump_traceback_later()  # armed for this test process

    stuck = (
        "import re, threading, time\n"
        "from robot_side.video import cli\n"
        "cli.AWAKE_S, cli.STALL_S = 0.05, 0.5\n"
        "def hog(): re.match(r'(a+)+$', 'a' * 30 + 'b')\n"
        "hogger = threading.Timer(0.3, hog)\n"  # once the server waits for its stop
        "hogger.daemon = True\n"
        "hogger.start()\n"
        "cli.wait_for_stop(threading.Event(), None)\n"
    )
    t0 = time.monotonic()
    done = subprocess.run([sys.executable, "-c", stuck], capture_output=True, text=True, timeout=30)
    took = time.monotonic() - t0
    assert done.returncode == 1, (done.returncode, done.stderr[-2000:])
    assert "Timeout" in done.stderr and "hog" in done.stderr, done.stderr[-2000:]
    assert took < 20, f"ended after {took:.1f} s, the hog alone runs for a minute"
