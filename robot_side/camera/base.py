"""The camera interface: what a video source gives the streamer.

A source is opened when the first viewer's encoder asks for a frame and
closed when the last viewer leaves, so a camera (or a simulated lab's
renderer) works only while someone watches. ``capture()`` blocks until the
next frame and returns it with the time it was taken; it runs on a worker
thread, never on the streaming loop.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class CapturedFrame:
    """One picture: ``rgb`` is height x width x 3, uint8; ``capture_ns`` is ``time.time_ns()``.

    Wall-clock time, so a browser on the same machine (or one whose clock is
    synchronised) can compute glass-to-glass latency from a stamped frame.
    """

    rgb: np.ndarray
    capture_ns: int


class VideoSource(abc.ABC):
    """A camera: ``open`` / ``capture`` / ``close``; ``name``, ``width``, ``height``, ``fps``."""

    name: str = "camera"
    width: int
    height: int
    fps: float

    @abc.abstractmethod
    def open(self) -> None:
        """Start capturing (open the device, start rendering); called on the first viewer."""

    @abc.abstractmethod
    def capture(self) -> CapturedFrame:
        """Block until the next frame, at the source's own pace, and return it."""

    @abc.abstractmethod
    def close(self) -> None:
        """Stop capturing; called when the last viewer leaves. ``open`` may follow again."""
