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
import os
import stat
import time
from typing import Any

from common.devices.preflight import (
    FAIL,
    WARN,
    Finding,
    PreflightContext,
    current_user_name,
    owner_text,
    processes_holding,
    service_user_can,
)
from common.errors import DeviceError, DeviceNotConnectedError
from robot_side.camera.base import Camera, CapturedFrame
from robot_side.camera.config import V4L2Config

log = logging.getLogger(__name__)


class V4L2Camera(Camera):
    Config = V4L2Config
    name = "v4l2"

    def __init__(self, config: V4L2Config | None = None) -> None:
        self.config = config or V4L2Config()
        self.width, self.height, self.fps = self.config.width, self.config.height, self.config.fps
        self._container: Any = None
        self._frames: Any = None

    @property
    def is_connected(self) -> bool:
        return self._frames is not None

    def connect(self) -> None:
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
            raise DeviceNotConnectedError("camera is not connected: connect() first")
        try:
            frame = next(self._frames)
        except StopIteration:
            raise DeviceError(f"camera {self.config.device} stopped delivering frames") from None
        t = time.time_ns()
        return CapturedFrame(frame.to_ndarray(format="rgb24"), t)

    def disconnect(self) -> None:
        container, self._container, self._frames = self._container, None, None
        if container is not None:
            container.close()
            log.info("camera %s closed", self.config.device)

    def _location(self) -> str:
        return f"on {self.config.device}"

    def _preflight(self, context: PreflightContext) -> list[Finding]:
        """Is the device node there, a device, ours and the service's to open, and free?"""
        c = self.config
        if c.format != "v4l2":  # an FFmpeg input (a file in tests): FFmpeg says what is wrong
            return []
        try:
            st = os.stat(c.device)
        except FileNotFoundError:
            return [
                Finding(
                    FAIL,
                    f"camera {c.device} does not exist",
                    "plug the camera in; `v4l2-ctl --list-devices` lists what is connected; "
                    f"set {context.where}.device to its /dev/video* or /dev/v4l/by-id/ name",
                )
            ]
        if not stat.S_ISCHR(st.st_mode):
            return [
                Finding(
                    FAIL,
                    f"{c.device} is not a character device",
                    f"set {context.where}.device to the camera",
                )
            ]
        if not os.access(c.device, os.R_OK | os.W_OK):
            return [
                Finding(
                    FAIL,
                    f"no permission to open {c.device} ({owner_text(st)}) as {current_user_name()}",
                    "add the user to video (`sudo usermod -aG video $USER`, then log in again)",
                )
            ]
        allowed, _service = service_user_can(st, context, os.R_OK | os.W_OK)
        if not allowed:
            return [
                Finding(
                    FAIL,
                    f"the service user {context.service_user} cannot open {c.device} "
                    f"({owner_text(st)})",
                    "deepxpalm-video.service runs with SupplementaryGroups=video: the camera "
                    "needs GROUP=video (the distribution's default udev rule)",
                )
            ]
        users = processes_holding({os.path.realpath(c.device)})
        if users:
            pid, cmd = users[0]
            return [
                Finding(
                    WARN,
                    f"{c.device} is open in pid {pid} ({cmd[:80]})",
                    "a camera streams to one program at a time: stop that one "
                    "(`systemctl stop deepxpalm-video` if it is the video server)",
                )
            ]
        return []
