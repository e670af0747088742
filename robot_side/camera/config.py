"""Each camera kind's typed config, apart from its driver.

The video config holds one of each (``[video.v4l2]``, ``[video.test_pattern]``,
``[video.lab]``) so ``--help`` and ``--print-config`` describe every kind;
keeping them here means reading the config imports no driver (PyAV, sockets).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from common.config.typed import param


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


@dataclass
class TestPatternConfig:
    __test__ = False  # not a pytest class, whatever its name says
    width: int = param(640, "pixels; at least 160 (the time stamp needs 40 cells of 4 px)")
    height: int = param(480, "pixels")
    fps: float = param(30.0, "frames per second")

    def __post_init__(self) -> None:
        if self.width < 160 or self.height < 32 or self.width % 2 or self.height % 2:
            raise ValueError("test pattern needs an even size of at least 160 x 32")
        if not 1 <= self.fps <= 120:
            raise ValueError(f"test pattern fps must be 1..120, not {self.fps}")


@dataclass
class LabCameraConfig:
    addresses_file: Path | None = param(
        None, "the running world's addresses (python -m robot_side.lab --addresses-file)"
    )
    camera: str = param("overview", "which of the world's cameras: overview or wrist")
    width: int = param(320, "pixels")
    height: int = param(240, "pixels")
    fps: float = param(
        5.0, "frames per second; each costs the world a render (tens of ms on a CPU)"
    )

    def __post_init__(self) -> None:
        if not 0.5 <= self.fps <= 30:
            raise ValueError(f"lab camera fps must be 0.5..30, not {self.fps}")
        if self.width % 2 or self.height % 2 or min(self.width, self.height) < 32:
            raise ValueError("lab camera needs an even size of at least 32 x 32")
