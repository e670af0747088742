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

Several viewers at once (``many_viewers``, ``watch``): aiortc peers in this
process, speaking the video server's own signalling (``{"type": "offer"}`` on
its WebSocket), so the server can run in another process and its crash is
seen from outside, as a browser would see it. Each decoded frame's capture
time is read back from the test pattern's stamp (``robot_side/camera/stamp.py``)
on the luma plane, without converting the frame: glass-to-glass here is
capture to decoded frame (a browser adds its paint, a few ms). A stall there is
a gap of over ``STALL_MS`` between two decoded frames of one viewer.

As a bench section: glass-to-glass video latency, robot camera to the operator's browser.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from harness.bench.fmt import results_of
from harness.bench.section import Context, Results, Section, Verdict
from harness.processes import idle_share, machine_cpu
from robot_side.camera.stamp import MS_MODULO, cell_size, read_stamp

WARMUP_FRAMES = 30  # the first second: ICE, keyframe, the receiver's buffer settling
STALL_MS = 500.0


@contextlib.contextmanager
def all_cores() -> Iterator[None]:
    """The browser and the encoder are processes and threads of their own: unpin them."""
    from harness.bench.timing import original_affinity

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
    from harness.bench.timing import machine_load
    from harness.headless_chromium import Chromium
    from operator_side.dashboard import Dashboard, DashboardConfig
    from operator_side.node import OperatorNode
    from operator_side.node.config import OperatorConfig
    from operator_side.servos.in_memory import InMemoryServoBus
    from robot_side.camera.config import TestPatternConfig
    from robot_side.camera.test_pattern import TestPatternCamera
    from robot_side.video.server import VideoConfig, VideoServer

    load_before = machine_load()
    source = TestPatternCamera(TestPatternConfig(width=width, height=height, fps=fps))
    node = OperatorNode(OperatorConfig(), InMemoryServoBus())  # the page needs a node; idle
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
        "unreadable_at": summary.get("unreadable_at", []),  # their indices among those shown
        "wall_s": round(wall_s, 1),
        # this process: capture, VP8 encoding, SRTP (the robot's side) and the dashboard
        "server_cpu_share": round(cpu_s / wall_s, 3),
        "page_errors": errors,
        "source_opened": source.opened,
        "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
        "load_before": load_before,
        "load_after": machine_load(),
    }


STALL_MS = 500.0
WARMUP_S = 1.0  # ICE, the first keyframe, the receiver's buffer settling


@dataclass
class ViewerRun:
    """What one viewer saw: per stamped frame its latency (ms) and arrival (monotonic s)."""

    latencies_ms: list[float] = field(default_factory=list)
    arrivals_s: list[float] = field(default_factory=list)
    unreadable: int = 0
    ended: str | None = None  # why it stopped before its time, when it did

    def gaps_ms(self) -> np.ndarray:
        """Gaps between decoded frames after the warm-up."""
        t = np.asarray(self.arrivals_s)
        if t.size < 2:
            return np.zeros(0)
        t = t[t >= t[0] + WARMUP_S]
        return np.diff(t) * 1e3

    def summary(self) -> dict[str, Any]:
        t = np.asarray(self.arrivals_s)
        lat = np.asarray(self.latencies_ms)[t >= t[0] + WARMUP_S] if t.size else np.zeros(0)
        gaps = self.gaps_ms()
        pct = (lambda p: round(float(np.percentile(lat, p)), 1)) if lat.size else (lambda p: None)
        return {
            "frames": int(t.size),
            "p50_ms": pct(50),
            "p99_ms": pct(99),
            "longest_gap_ms": round(float(gaps.max()), 1) if gaps.size else None,
            "stalls": int(np.sum(gaps > STALL_MS)),
            "unreadable": self.unreadable,
            "ended": self.ended,
        }


def _stamp_of(frame: Any) -> tuple[int, int] | None:
    """The stamp read from the top rows of the luma plane (no colour conversion)."""
    plane = frame.planes[0]
    rows = 2 * cell_size(frame.width)
    luma = np.frombuffer(plane, np.uint8).reshape(-1, plane.line_size)[:rows, : frame.width]
    return read_stamp(luma[..., None])


async def view(url: str, seconds: float, run: ViewerRun) -> None:
    """Offer to the video server at ``url`` and time what is decoded for ``seconds``."""
    from aiortc import RTCConfiguration, RTCPeerConnection, RTCSessionDescription
    from websockets.asyncio.client import connect

    pc = RTCPeerConnection(RTCConfiguration(iceServers=[]))
    pc.addTransceiver("video", direction="recvonly")
    track_ready: asyncio.Future = asyncio.get_running_loop().create_future()
    pc.on("track", lambda t: track_ready.done() or track_ready.set_result(t))
    await pc.setLocalDescription(await pc.createOffer())
    try:
        async with connect(url, open_timeout=10, max_size=2**20) as ws:
            await ws.send(json.dumps({"type": "offer", "sdp": pc.localDescription.sdp}))
            answer = json.loads(await asyncio.wait_for(ws.recv(), 15))
            await pc.setRemoteDescription(RTCSessionDescription(answer["sdp"], "answer"))
            track = await asyncio.wait_for(track_ready, 15)
            end = time.monotonic() + seconds
            while (left := end - time.monotonic()) > 0:
                frame = await asyncio.wait_for(track.recv(), min(left, 5.0) + 0.5)
                now_ms = time.time_ns() // 1_000_000
                stamp = _stamp_of(frame)
                if stamp is None:
                    run.unreadable += 1
                    continue
                run.arrivals_s.append(time.monotonic())
                run.latencies_ms.append(float((now_ms - stamp[0]) % MS_MODULO))
    except Exception as e:  # the server died, refused or went silent: said in the result
        run.ended = f"{type(e).__name__}: {e}"[:200]
    finally:
        await pc.close()


async def watch(url: str, viewers: int, seconds: float) -> list[ViewerRun]:
    """``viewers`` viewers at once on the server at ``url``, each for ``seconds``."""
    runs = [ViewerRun() for _ in range(viewers)]
    await asyncio.gather(*(view(url, seconds, run) for run in runs))
    return runs


def many_viewers(
    viewers: int, seconds: float, width: int = 640, height: int = 480, fps: float = 30.0
) -> dict[str, Any]:
    """``viewers`` viewers at once on a video server in this process, for the bench."""
    from robot_side.camera.config import TestPatternConfig
    from robot_side.camera.test_pattern import TestPatternCamera
    from robot_side.video.server import VideoConfig, VideoServer

    source = TestPatternCamera(TestPatternConfig(width=width, height=height, fps=fps))
    cpu0 = machine_cpu()
    with VideoServer(source, VideoConfig(port=0, max_viewers=viewers)) as server:
        runs = asyncio.run(watch(server.url, viewers, seconds))
    lat = np.concatenate([np.asarray(r.latencies_ms) for r in runs] + [np.zeros(0)])
    each = [r.summary() for r in runs]
    return {
        "viewers": viewers,
        "seconds": seconds,
        "p50_ms": round(float(np.percentile(lat, 50)), 1) if lat.size else None,
        "p99_ms": round(float(np.percentile(lat, 99)), 1) if lat.size else None,
        "stalls_over_500ms": sum(v["stalls"] for v in each),
        "longest_gap_ms": max((v["longest_gap_ms"] or 0.0) for v in each),
        "fps_per_viewer": round(min(v["frames"] for v in each) / seconds, 1),
        "fps_per_viewer_max": round(max(v["frames"] for v in each) / seconds, 1),
        "fps_source": fps,
        "ended_early": sum(v["ended"] is not None for v in each),
        "machine_idle_cpu": round(idle_share(cpu0, machine_cpu()), 3),
    }


TITLE = "Video: glass to glass"

#: the goal for the median latency
P50_GOAL_MS = 80.0


@dataclass(frozen=True)
class VideoSizes:
    video_frames: int  # stamped frames read in the browser (30 a second)
    viewers_s: float  # four aiortc viewers at once, this long


SIZES = {
    "full": VideoSizes(video_frames=1200, viewers_s=60.0),
    "quick": VideoSizes(video_frames=300, viewers_s=20.0),
    "smallest": VideoSizes(video_frames=30, viewers_s=3.0),
}
VIEWERS = 4


def measure(ctx: Context, sizes: VideoSizes) -> dict[str, Any]:
    out = glass_to_glass(sizes.video_frames)
    with all_cores():
        out["many_viewers"] = many_viewers(VIEWERS, sizes.viewers_s)
    return out


def verdicts(results: Results) -> list[Verdict]:
    """The goal stated in the section's own text, then the four viewers'."""
    s = results_of(results, "video")
    if s is None:
        return []
    lat = s["latency_ms"]
    out = [
        Verdict(
            f"p50 under {P50_GOAL_MS:g} ms and no stall over {STALL_MS:g} ms",
            f"p50 {lat['p50']:.0f} ms, {s['stalls_over_500ms']} stalls",
            lat["p50"] < P50_GOAL_MS and s["stalls_over_500ms"] == 0,
            table=None,
        )
    ]
    m = s.get("many_viewers")
    if m:
        out.append(many_viewers_verdict(m))
    return out


def many_viewers_verdict(m: dict[str, Any]) -> Verdict:
    """Several viewers at once: each served to the end at a quarter of the source's rate or
    more, alike within 20 %, no gap over ``STALL_MS``, glass-to-glass p50 under the goal."""
    p50 = m["p50_ms"]
    alike = m.get("fps_per_viewer_max") is None or (
        m["fps_per_viewer"] >= 0.8 * m["fps_per_viewer_max"]
    )
    passed = (
        p50 is not None
        and p50 < P50_GOAL_MS
        and m["stalls_over_500ms"] == 0
        and m["ended_early"] == 0
        # results stored before the source's rate was: the default, 30 fps
        and m["fps_per_viewer"] >= 0.25 * m.get("fps_source", 30.0)
        and alike
    )
    return Verdict(
        f"video: {m['viewers']} viewers, none cut off, each at a quarter of the source's rate "
        f"or more and alike, no stall over {STALL_MS:g} ms, p50 under {P50_GOAL_MS:g} ms",
        f"p50 {p50} ms, slowest {m['fps_per_viewer']} fps, {m['stalls_over_500ms']} stalls, "
        f"{m['ended_early']} cut off",
        passed,
    )


def markdown(results: Results) -> list[str]:
    """Nothing when the section did not run."""
    section = results_of(results, "video")
    if not section:
        return []
    lat = section["latency_ms"]
    goal = verdicts(results)[0]  # the four viewers' verdict has a table of its own
    verdict = "passes" if goal.passed else "fails"
    return [
        "",
        f"## {TITLE}",
        "",
        f"The stamped test pattern ({section['width']}x{section['height']} at "
        f"{section['fps_source']:g} fps) from the robot's video server (aiortc, VP8, WebRTC "
        "on loopback) to the dashboard in headless chromium, which reads each presented "
        "frame's capture time back from its pixels (`harness/bench/video.py`). "
        f"{section['frames']} frames after a {WARMUP_FRAMES}-frame warm-up; the goal is "
        f"{goal.what}: it {verdict}. Measured {section['date']}, "
        f"machine load (1 min) {section['load_before']['loadavg_1m']} before and "
        f"{section['load_after']['loadavg_1m']} after, on a machine shared with other work.",
        "",
        "| frames | p50 ms | p90 ms | p99 ms | max ms | presented fps | longest gap ms "
        "| stalls > 500 ms | frames not presented | sender CPU (share of a core) |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
        f"| {section['frames']} | {lat['p50']:.0f} | {lat['p90']:.0f} | {lat['p99']:.0f} | "
        f"{lat['max']:.0f} | {section['fps_presented']} | {section['longest_gap_ms']:.0f} | "
        f"{section['stalls_over_500ms']} | {section['skipped_frames']} | "
        f"{section.get('server_cpu_share', float('nan')):.2f} |",
        *_many_viewers(section.get("many_viewers")),
        "",
        "Not measured here: the link simulator scenarios (the `video_netsim` section plays "
        "the same page through them), and a real camera's exposure and USB transfer, which "
        "come before the stamp.",
    ]


def _many_viewers(m: dict[str, Any] | None) -> list[str]:
    if not m:
        return []
    return [
        "",
        f"{m['viewers']} viewers at once for {m['seconds']:g} s, the same pattern, each an "
        "aiortc receiver in the bench's process timing capture to decoded frame "
        f"(`harness/bench/video.py`): p50 {m['p50_ms']} ms, p99 {m['p99_ms']} ms, "
        f"{m['fps_per_viewer']} fps for the slowest viewer, longest gap "
        f"{m['longest_gap_ms']:.0f} ms, {m['stalls_over_500ms']} stalls over 500 ms, "
        f"{m['ended_early']} viewers cut off; the machine's CPU was "
        f"{m['machine_idle_cpu']:.0%} idle. {_passes(many_viewers_verdict(m))}",
    ]


def _passes(v: Verdict) -> str:
    return f"Goal: {v.what}: it {'passes' if v.passed else 'fails'}."


SECTION = Section(
    name="video",
    title=TITLE,
    sizes=SIZES,
    measure=measure,
    markdown=markdown,
    verdicts=verdicts,
    quick=False,
)
