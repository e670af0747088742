"""A USB camera on the robot PC through Video4Linux2, read with PyAV (FFmpeg's v4l2 input).

The device is opened when the first viewer arrives and closed when the last
one leaves, so the camera's light is on only while someone watches. The
capture time is the wall clock when the frame is dequeued: it leaves out
the exposure and the USB transfer (a few milliseconds to one frame period),
so latency measured from it is a slight underestimate; the test pattern
has no such gap.

``input_format`` picks the camera's wire format: most USB cameras give
640x480 at 30 fps only as MJPEG (raw YUYV often tops out at lower rates
over USB 2). ``format`` and ``device`` may name any FFmpeg input (a file
with ``format = "matroska"``): that is how the decoding path is tested on a
machine without a camera.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any

from common.config import param
from common.errors import DeviceError, DeviceNotConnectedError
from robot_side.video.source import CapturedFrame, VideoSource

log = logging.getLogger(__name__)


@dataclass
class V4L2Config:
    device: str = param("/dev/video0", "the camera's device node (v4l2-ctl --list-devices)")
    width: int = param(640, "requested width; the camera may choose the nearest it has")
    height: int = param(480, "requested height")
    fps: float = param(30.0, "requested frame rate")
    input_format: str = param(
        "mjpeg", "the camera's wire format: mjpeg (most 640x480@30 cameras) or yuyv422"
    )
    format: str = param("v4l2", "FFmpeg input format; v4l2 for a camera")


class V4L2Source(VideoSource):
    name = "v4l2"

    def __init__(self, config: V4L2Config | None = None) -> None:
        self.config = config or V4L2Config()
        self.width, self.height, self.fps = self.config.width, self.config.height, self.config.fps
        self._container: Any = None
        self._frames: Any = None

    def open(self) -> None:
        import av

        c = self.config
        options = {}
        if c.format == "v4l2":
            options = {
                "video_size": f"{c.width}x{c.height}",
                "framerate": f"{c.fps:g}",
                "input_format": c.input_format,
            }
        try:
            self._container = av.open(c.device, format=c.format, options=options)
        except (OSError, av.error.FFmpegError) as e:
            raise DeviceNotConnectedError(
                f"camera {c.device} ({c.format}) could not be opened: {e}; check that it is "
                "plugged in (v4l2-ctl --list-devices), that this user is in the 'video' group, "
                "and that no other program holds it"
            ) from e
        stream = self._container.streams.video[0]
        stream.thread_type = "AUTO"
        self.width, self.height = stream.codec_context.width, stream.codec_context.height
        self._frames = self._container.decode(stream)
        log.info("camera %s open: %dx%d", c.device, self.width, self.height)

    def capture(self) -> CapturedFrame:
        if self._frames is None:
            raise DeviceNotConnectedError("camera is not open: open() first")
        try:
            frame = next(self._frames)
        except StopIteration:
            raise DeviceError(f"camera {self.config.device} stopped delivering frames") from None
        t = time.time_ns()
        return CapturedFrame(frame.to_ndarray(format="rgb24"), t)

    def close(self) -> None:
        container, self._container, self._frames = self._container, None, None
        if container is not None:
            container.close()
            log.info("camera %s closed", self.config.device)
