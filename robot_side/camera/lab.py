"""A simulated lab's camera: frames the world renders when asked.

The world process (``python -m robot_side.lab --addresses-file F``, or the
demo's) serves its cameras on a loopback socket (``robot_side/lab/
camera_server.py``); its port is in the addresses file. This camera asks for
one frame per period while it is connected, so the world renders only while
someone watches. No MuJoCo here: the video process speaks to the socket.
"""

from __future__ import annotations

import json
import logging
import socket
import time
from pathlib import Path

import numpy as np

from common.errors import ConfigError, DeviceError, DeviceNotConnectedError
from robot_side.camera.base import Camera, CapturedFrame
from robot_side.camera.config import LabCameraConfig

log = logging.getLogger(__name__)


class LabCamera(Camera):
    """Frames from a running world's camera socket, at ``fps``, while connected."""

    Config = LabCameraConfig
    simulated = True  # the world renders it

    def __init__(self, config: LabCameraConfig) -> None:
        if config.addresses_file is None:
            raise ConfigError("video source 'lab' needs lab.addresses_file (the world's addresses)")
        self.config = config
        self.name = f"lab {config.camera}"
        self.width, self.height, self.fps = config.width, config.height, config.fps
        self._sock: socket.socket | None = None
        self._reader = None
        self._next_s = 0.0
        self.render_ms: list[float] = []

    @property
    def is_connected(self) -> bool:
        return self._sock is not None

    def connect(self) -> None:
        path = self.config.addresses_file
        try:
            port = int(json.loads(Path(path).read_text())["camera_port"])
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise DeviceError(f"lab camera: no camera_port in {path}: {e}") from None
        try:
            self._sock = socket.create_connection(("127.0.0.1", port), timeout=30.0)
        except OSError as e:
            raise DeviceError(f"lab camera: the world's camera socket {port}: {e}") from None
        self._reader = self._sock.makefile("rb")
        self._next_s = time.monotonic()

    def capture(self) -> CapturedFrame:
        if self._sock is None:
            raise DeviceNotConnectedError("lab camera is not connected: connect() first")
        delay = self._next_s - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        self._next_s = max(self._next_s + 1.0 / self.fps, time.monotonic())
        c = self.config
        request = {"camera": c.camera, "width": c.width, "height": c.height}
        taken_ns = time.time_ns()
        try:
            self._sock.sendall(json.dumps(request).encode() + b"\n")
            header = json.loads(self._reader.readline(4096) or b"{}")
            if "error" in header or "width" not in header:
                raise DeviceError(f"lab camera: the world says {header.get('error', 'nothing')}")
            size = header["width"] * header["height"] * 3
            payload = self._reader.read(size)
        except (OSError, ValueError) as e:
            raise DeviceError(f"lab camera: the world's camera socket failed: {e}") from None
        if len(payload) != size:
            raise DeviceError("lab camera: the world closed its camera socket mid-frame")
        self.render_ms.append(float(header.get("render_ms", 0.0)))
        rgb = np.frombuffer(payload, np.uint8).reshape(header["height"], header["width"], 3)
        return CapturedFrame(rgb=rgb, capture_ns=taken_ns)

    def disconnect(self) -> None:
        for closable in (self._reader, self._sock):
            if closable is not None:
                closable.close()
        self._reader = self._sock = None
