"""The camera in a session's recording: JPEG frames at ``record_fps`` in an MCAP of its own.

The video server owns the camera (a V4L2 device opens once), so it is the
video server that records it, into its own file beside the robot node's
(``camera.mcap`` next to ``robot.mcap``), while it runs with ``record`` set.
Both files stamp records with ``time.monotonic_ns`` of the same machine, so
a camera frame and a tactile frame are on one clock without any exchange
between the two processes (docs/recording.md).

Frames are taken from the feed's capture thread at most ``record_fps`` a
second, handed to an encoder thread through a two-frame queue (a frame the
encoder cannot take in time is dropped and counted, never queued without
bound), coded as JPEG by PyAV's ``mjpeg`` encoder, and written as bytes
(base64 in the JSON record, as every byte field of a recording).
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
from fractions import Fraction
from pathlib import Path
from typing import Any

from common.clocks.clock import wall_offset_ns
from common.recording.mcap_recorder import McapRecorder
from robot_side.camera.base import CapturedFrame
from robot_side.video.feed import CameraFeed

log = logging.getLogger(__name__)

CHANNEL = "camera/image"
JPEG_QUALITY = 3  # FFmpeg's qscale for mjpeg: 2 best .. 31 worst; 3 is about JPEG quality 90


class CameraRecording:
    """Records ``feed``'s frames at ``fps`` into ``path``; ``start()`` / ``stop()``."""

    def __init__(
        self,
        feed: CameraFeed,
        path: Path,
        fps: float,
        camera: str,
        metadata: dict[str, dict[str, str]] | None = None,
    ) -> None:
        self.feed = feed
        self.path = Path(path)
        self.period_ns = round(1e9 / fps)
        self.camera = camera
        self._metadata = {
            **(metadata or {}),
            "deepxpalm.camera": {"camera": camera, "record_fps": f"{fps:g}", "format": "jpeg"},
        }
        self._queue: queue.Queue[tuple[CapturedFrame, int] | None] = queue.Queue(maxsize=2)
        self._next_due: int | None = None
        self._recorder: McapRecorder | None = None
        self._thread: threading.Thread | None = None
        self.frames_recorded = 0
        self.frames_dropped = 0

    def start(self) -> CameraRecording:
        self._recorder = McapRecorder(self.path, metadata=self._metadata)
        self._thread = threading.Thread(target=self._encode, name="camera-record", daemon=True)
        self._thread.start()
        self.feed.add_listener(self._offer)
        self.feed.subscribe("recording")
        log.info(
            "video: recording %s at %g fps into %s", self.camera, 1e9 / self.period_ns, self.path
        )
        return self

    def stop(self, timeout_s: float = 10.0) -> None:
        """Stop taking frames, write what is queued, close the file.

        Waits at most ``timeout_s`` for the encoder to finish what is queued."""
        if self._recorder is None:
            return
        self.feed.unsubscribe("recording")
        self.feed.remove_listener(self._offer)
        # the end mark must get in even when the encoder is behind and the queue full (a
        # blocking put waited on it for ever, and systemd's stop then had to SIGKILL): the
        # oldest queued frame makes room, counted as dropped
        while True:
            try:
                self._queue.put_nowait(None)
                break
            except queue.Full:
                with contextlib.suppress(queue.Empty):
                    if self._queue.get_nowait() is not None:
                        self.frames_dropped += 1
        if self._thread is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                log.error(
                    "video: the %s recording's encoder did not finish in %g s",
                    self.camera,
                    timeout_s,
                )
        self._recorder.close()
        self._recorder = None
        log.info(
            "video: recorded %d frames of %s (%d dropped: the encoder fell behind)",
            self.frames_recorded,
            self.camera,
            self.frames_dropped,
        )

    def _offer(self, frame: CapturedFrame) -> None:
        """On the capture thread: keep the frame nearest each period's tick (monotonic clock).

        A frame half a camera period before the tick is nearer to it than the
        next one: taking only frames at or after the tick would drift to the
        camera's next multiple (7.5 fps from a 15 fps camera at 10).
        """
        t_ns = frame.capture_ns - wall_offset_ns()
        early_ns = 5e8 / self.feed.camera.fps
        if self._next_due is not None and t_ns + early_ns < self._next_due:
            return
        # the next is due one period on; a stall restarts the schedule instead of bursting
        due = (self._next_due or t_ns) + self.period_ns
        self._next_due = due if due > t_ns else t_ns + self.period_ns
        try:
            self._queue.put_nowait((frame, t_ns))
        except queue.Full:
            self.frames_dropped += 1

    def _encode(self) -> None:
        encoder: Any = None
        size: tuple[int, int] | None = None
        while True:
            item = self._queue.get()
            if item is None:
                return
            frame, t_ns = item
            h, w, _ = frame.rgb.shape
            if (w, h) != size:  # a camera may change size when it reconnects
                encoder, size = _jpeg_encoder(w, h), (w, h)
            try:
                data = _jpeg(encoder, frame)
            except Exception:  # one bad frame must not end the recording
                log.exception("video: a frame of %s could not be coded", self.camera)
                continue
            recorder = self._recorder
            if recorder is None:  # stop() gave up waiting for this frame and closed the file
                return
            recorder.write(
                CHANNEL,
                t_ns,
                {
                    "camera": self.camera,
                    "format": "jpeg",
                    "width": w,
                    "height": h,
                    "frame_index": self.frames_recorded,
                    "t_capture_ns": t_ns,
                    "capture_wall_ns": frame.capture_ns,
                    "data": data,
                },
            )
            self.frames_recorded += 1


def _jpeg_encoder(width: int, height: int) -> Any:
    import av

    ctx = av.CodecContext.create("mjpeg", "w")
    ctx.width, ctx.height, ctx.pix_fmt = width, height, "yuvj420p"
    ctx.time_base = Fraction(1, 1000)
    ctx.qmin = ctx.qmax = JPEG_QUALITY
    return ctx


def _jpeg(encoder: Any, frame: CapturedFrame) -> bytes:
    import av

    picture = av.VideoFrame.from_ndarray(frame.rgb, format="rgb24").reformat(format="yuvj420p")
    return b"".join(bytes(p) for p in encoder.encode(picture))


def decode_jpeg(data: bytes) -> Any:
    """A recorded frame's JPEG bytes back to RGB (height x width x 3, uint8)."""
    import av

    decoder = av.CodecContext.create("mjpeg", "r")
    return decoder.decode(av.Packet(data))[0].to_ndarray(format="rgb24")
