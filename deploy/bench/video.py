"""Glass-to-glass video latency: robot camera to the operator's browser, measured in the browser.

The stamped test pattern (640x480, 30 fps) goes through the robot's video
server (aiortc, VP8, WebRTC over loopback UDP) to the dashboard page in
headless chromium, whose signalling the dashboard server relays. The page
reads each presented frame's capture time back from its pixels
(``requestVideoFrameCallback``, then the stamp) and subtracts it from its own
wall clock: capture, encode, packetise, send, jitter buffer, decode and
presentation are all inside the number. Only the glass itself (the display's
scan-out, a few ms to a frame) is not.

A stall is the longest time between two presented frames.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Iterator
from typing import Any

import numpy as np

WARMUP_FRAMES = 30  # the first second: ICE, keyframe, the receiver's buffer settling
STALL_MS = 500.0


@contextlib.contextmanager
def all_cores() -> Iterator[None]:
    """The browser and the encoder are processes and threads of their own: unpin them."""
    from deploy.bench.timing import original_affinity

    before = os.sched_getaffinity(0)
    os.sched_setaffinity(0, original_affinity())
    try:
        yield
    finally:
        os.sched_setaffinity(0, before)


def glass_to_glass(
    frames: int, width: int = 640, height: int = 480, fps: float = 30.0
) -> dict[str, Any]:
    """p50/p90/p99/max latency (ms), stalls and skipped frames over ``frames`` stamped frames."""
    from deploy.bench.timing import machine_load
    from deploy.headless_chromium import Chromium
    from operator_side.config import OperatorConfig
    from operator_side.dashboard import Dashboard, DashboardConfig
    from operator_side.node import OperatorNode
    from operator_side.servos.recording import RecordingServoBus
    from robot_side.camera.config import TestPatternConfig
    from robot_side.camera.test_pattern import TestPatternCamera
    from robot_side.video.server import VideoConfig, VideoServer

    load_before = machine_load()
    source = TestPatternCamera(TestPatternConfig(width=width, height=height, fps=fps))
    node = OperatorNode(OperatorConfig(), RecordingServoBus())  # the page needs a node; idle
    want = frames + WARMUP_FRAMES
    timeout_s = 30 + 3 * want / fps
    with all_cores(), VideoServer(source, VideoConfig(port=0)) as server:
        dashboard = Dashboard(node, DashboardConfig(port=0, video_url=server.url))
        dashboard.start()
        try:
            with Chromium(width=1280, height=900) as browser:
                t0 = time.monotonic()
                cpu0 = time.process_time()
                browser.navigate(dashboard.url)
                browser.wait_until(
                    "dxp.video ? dxp.video.latencies.length : 0",
                    lambda n: n >= want,
                    timeout_s=timeout_s,
                    poll_s=0.5,
                )
                wall_s = time.monotonic() - t0
                cpu_s = time.process_time() - cpu0
                data = browser.evaluate(
                    "({lat: dxp.video.latencies, shown: dxp.video.presented, "
                    "summary: dxp.video.summary()})"
                )
                errors = browser.page_errors()
        finally:
            dashboard.stop()
    lat = np.asarray(data["lat"][WARMUP_FRAMES:], dtype=np.float64)
    shown = np.asarray(data["shown"], dtype=np.float64)[WARMUP_FRAMES:]
    gaps = np.diff(shown) if shown.size > 1 else np.zeros(1)
    span_s = (shown[-1] - shown[0]) / 1e3 if shown.size > 1 else float("nan")
    summary = data["summary"]
    return {
        "frames": int(lat.size),
        "width": width,
        "height": height,
        "fps_source": fps,
        "fps_presented": round(float((shown.size - 1) / span_s), 2) if span_s > 0 else None,
        "latency_ms": {
            "p50": float(np.percentile(lat, 50)),
            "p90": float(np.percentile(lat, 90)),
            "p99": float(np.percentile(lat, 99)),
            "max": float(lat.max()),
            "min": float(lat.min()),
        },
        "longest_gap_ms": float(gaps.max()),
        "stalls_over_500ms": int(np.sum(gaps > STALL_MS)),
        "skipped_frames": int(summary["skipped"]),
        "unreadable_frames": int(summary["unreadable"]),
        "wall_s": round(wall_s, 1),
        # this process: capture, VP8 encoding, SRTP (the robot's side) and the dashboard
        "server_cpu_share": round(cpu_s / wall_s, 3),
        "page_errors": errors,
        "source_opened": source.opened,
        "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
        "load_before": load_before,
        "load_after": machine_load(),
    }
