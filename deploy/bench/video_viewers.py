"""Several WebRTC viewers of one video server, each timing the stamped frames it decodes.

The viewers are aiortc peers in this process, speaking the video server's own
signalling (``{"type": "offer"}`` on its WebSocket), so the server can run in
another process and its crash is seen from outside, as a browser would see
it. Each decoded frame's capture time is read back from the test pattern's
stamp (``robot_side/video/stamp.py``) on the luma plane, without converting
the frame: glass-to-glass here is capture to decoded frame (a browser adds
its paint, a few ms). A stall is a gap of over ``STALL_MS`` between two
decoded frames of one viewer.
"""

from __future__ import annotations

import asyncio
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from robot_side.video.stamp import MS_MODULO, cell_size, read_stamp

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
    cpu0 = cpu_times()
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
        "ended_early": sum(v["ended"] is not None for v in each),
        "machine_idle_cpu": round(idle_share(cpu0, cpu_times()), 3),
    }


def cpu_times() -> tuple[float, float]:
    """(idle, total) jiffies of the whole machine since boot (Linux ``/proc/stat``)."""
    fields = [float(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    return fields[3] + fields[4], sum(fields[:8])  # idle + iowait; user .. steal


def idle_share(before: tuple[float, float], after: tuple[float, float]) -> float:
    """Share of the machine's CPU time left idle between two ``cpu_times()`` readings."""
    total = after[1] - before[1]
    return (after[0] - before[0]) / total if total > 0 else 0.0
