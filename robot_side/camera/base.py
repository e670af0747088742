"""The camera interface: what a camera gives the video streamer.

A camera is a ``Device``: it is connected when the first viewer's encoder
asks for a frame and disconnected when the last viewer leaves, so a camera
(or a simulated lab's renderer) works only while someone watches.
``capture()`` blocks until the next frame and returns it with the time it
was taken; it runs on a worker thread, never on the streaming loop.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from common.devices.lifecycle import Device, load_object
from common.errors import ConfigError


@dataclass(frozen=True)
class CapturedFrame:
    """One picture: ``rgb`` is height x width x 3, uint8; ``capture_ns`` is ``time.time_ns()``.

    Wall-clock time, so a browser on the same machine (or one whose clock is
    synchronised) can compute glass-to-glass latency from a stamped frame.
    """

    rgb: np.ndarray
    capture_ns: int


class Camera(Device):
    """A camera: ``connect`` / ``capture`` / ``disconnect``; ``width`` x ``height`` at ``fps``.

    ``connect`` may follow ``disconnect`` again (the next viewer).
    """

    family: ClassVar[str] = "camera"
    name: str = "camera"
    width: int
    height: int
    fps: float

    @abc.abstractmethod
    def capture(self) -> CapturedFrame:
        """Block until the next frame, at the camera's own pace, and return it."""

    def status(self) -> dict[str, Any]:
        return {
            **super().status(),
            "name": self.name,
            "width": self.width,
            "height": self.height,
            "fps": self.fps,
        }


def build_camera(kind: str, config: Any) -> Camera:
    """The camera of ``kind`` (a key of ``robot_side.camera.KINDS``) built from its typed config."""
    from robot_side.camera import KINDS

    if kind not in KINDS:
        raise ConfigError(f"video source {kind!r} is not one of {sorted(KINDS)}")
    cls = load_object(KINDS[kind])
    if not isinstance(config, cls.Config):
        raise ConfigError(
            f"video source {kind!r} takes a {cls.Config.__name__}, not {type(config).__name__}"
        )
    return cls(config)
