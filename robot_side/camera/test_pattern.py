"""A moving test picture with its capture time stamped into it, for measuring latency.

Colour bars scrolling sideways and a bouncing square: enough motion that
the encoder works as it would on a camera (a still picture codes to almost
nothing and would flatter the latency). Paced on its own clock at ``fps``.
"""

from __future__ import annotations

import time

import numpy as np

from robot_side.camera.base import Camera, CapturedFrame
from robot_side.camera.config import TestPatternConfig
from robot_side.camera.stamp import draw_stamp

BARS = np.array(
    [
        [192, 192, 192],
        [192, 192, 0],
        [0, 192, 192],
        [0, 192, 0],
        [192, 0, 192],
        [192, 0, 0],
        [0, 0, 192],
        [16, 16, 16],
    ],
    dtype=np.uint8,
)


class TestPatternCamera(Camera):
    """Frames stamped with ``time.time_ns()`` at the moment they are made."""

    __test__ = False  # not a pytest class, whatever its name says
    Config = TestPatternConfig
    simulated = True  # no hardware: the picture is made here
    name = "test_pattern"

    def __init__(self, config: TestPatternConfig | None = None) -> None:
        self.config = config or TestPatternConfig()
        self.width, self.height, self.fps = self.config.width, self.config.height, self.config.fps
        cols = np.linspace(0, len(BARS), 2 * self.width, endpoint=False).astype(int) % len(BARS)
        self._bars = np.ascontiguousarray(
            np.broadcast_to(BARS[cols][None], (self.height, 2 * self.width, 3))
        )
        self._next = 0.0
        self._count = 0
        self._connected = False
        self.opened = 0  # times connected: a test can see that nothing runs without a viewer

    @property
    def is_connected(self) -> bool:
        return self._connected

    def connect(self) -> None:
        self._next = time.monotonic()
        self._connected = True
        self.opened += 1

    def capture(self) -> CapturedFrame:
        self.require_connected()
        self._next += 1.0 / self.fps
        delay = self._next - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        elif delay < -0.5:  # fell far behind (a stall): restart the clock, do not burst
            self._next = time.monotonic()
        n = self._count
        self._count += 1
        shift = (4 * n) % self.width
        rgb = self._bars[:, shift : shift + self.width].copy()
        side = self.height // 6
        x = int((self.width - side) * (0.5 + 0.5 * np.sin(n / 20)))
        y = int((self.height - side) * (0.5 + 0.5 * np.cos(n / 27)))
        rgb[y : y + side, x : x + side] = (255, 255, 255)
        t = time.time_ns()
        draw_stamp(rgb, t // 1_000_000, n)
        return CapturedFrame(rgb, t)

    def disconnect(self) -> None:
        self._connected = False
