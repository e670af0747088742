"""The camera as a WebRTC track every viewer's encoder shares (aiortc, imported lazily).

Each frame is converted to ``yuv420p`` once, on the capture thread, before
the relay hands the same frame object to every viewer's encoder: aiortc's
VP8 encoder reformats any other format on its own thread, and PyAV's
``reformat`` of one frame from two threads at once crashes the process or
hangs it (docs/dashboard.md, Video).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
from fractions import Fraction
from typing import Any

from common.wire.ice import IceConfig
from robot_side.camera.base import CapturedFrame
from robot_side.video.feed import CameraFeed

VIDEO_CLOCK = 90_000  # RTP's video clock rate
SHARED_FORMAT = "yuv420p"  # what the VP8 encoder takes as it is (no reformat on its thread)


def shareable(frame: CapturedFrame) -> Any:
    """``frame`` as a ``yuv420p`` VideoFrame every viewer's encoder may share."""
    import av

    rgb = av.VideoFrame.from_ndarray(frame.rgb, format="rgb24")
    return rgb.reformat(format=SHARED_FORMAT)


def source_track(feed: CameraFeed, thread_prefix: str) -> Any:
    """An aiortc track of ``feed``'s frames: subscribed on its first frame, until ``stop``.

    Frames are taken on a thread whose name starts with ``thread_prefix`` (the server's
    ``stop()`` waits for its threads by name)."""
    import av
    from aiortc import MediaStreamTrack
    from aiortc.mediastreams import MediaStreamError

    class SourceTrack(MediaStreamTrack):
        kind = "video"

        def __init__(self) -> None:
            super().__init__()
            self._pool = concurrent.futures.ThreadPoolExecutor(
                1, thread_name_prefix=f"{thread_prefix}-cap"
            )
            self._open = False
            self._seq = 0
            self._t0: int | None = None
            self.frames = 0

        def _next(self) -> tuple[CapturedFrame, Any]:
            # until stopped, or the feed closed (its next_frame then returns at once: no spin)
            while self.readyState == "live" and not feed.closed:
                got = feed.next_frame(self._seq, timeout_s=0.5)
                if got is not None:
                    self._seq, frame = got
                    return frame, shareable(frame)
            raise MediaStreamError

        async def recv(self) -> av.VideoFrame:
            if self.readyState != "live":
                raise MediaStreamError  # the relay's reader ends quietly
            loop = asyncio.get_running_loop()
            if not self._open:
                feed.subscribe("viewer")
                self._open = True
            try:
                frame, out = await loop.run_in_executor(self._pool, self._next)
            except RuntimeError:  # stopped meanwhile: the pool no longer takes work
                raise MediaStreamError from None
            if self._t0 is None:
                self._t0 = frame.capture_ns
            out.pts = (frame.capture_ns - self._t0) * VIDEO_CLOCK // 1_000_000_000
            out.time_base = Fraction(1, VIDEO_CLOCK)
            self.frames += 1
            return out

        def stop(self) -> None:
            super().stop()
            if self._open:
                self._open = False
                feed.unsubscribe("viewer")
            self._pool.shutdown(wait=False)

    return SourceTrack()


def rtc_configuration(ice: IceConfig) -> Any:
    """aiortc's configuration: exactly the configured servers (none: host candidates only).

    Left unset, aiortc would ask Google's public STUN server from the robot PC.
    """
    from aiortc import RTCConfiguration, RTCIceServer

    return RTCConfiguration(iceServers=[RTCIceServer(**server) for server in ice.as_dicts()])
