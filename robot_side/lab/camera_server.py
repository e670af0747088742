"""The world's cameras on a loopback socket, for a video source in another process.

A client sends one JSON line per frame it wants, ``{"camera": "overview",
"width": 320, "height": 240}``, and reads back one JSON line
(``{"width", "height", "sim_time_s", "render_ms"}``) followed by
``height * width * 3`` bytes of RGB, or ``{"error": ...}`` alone. So an image
is rendered only when a client asks for it: the video server asks only
while someone watches.

All rendering happens on one thread (the GL context is current on one
thread at a time), the same one the parent's ``camera_frame`` uses.
"""

from __future__ import annotations

import json
import logging
import socket
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future

import numpy as np

log = logging.getLogger(__name__)

#: the largest image a client may ask for (pixels a side)
MAX_SIDE = 1920
#: a request line longer than this is garbage
MAX_REQUEST_BYTES = 1024


class CameraServer:
    """``render(camera, width, height) -> Future[ndarray]`` served on 127.0.0.1:``port``."""

    def __init__(self, render: Callable[[str, int, int], Future], host: str = "127.0.0.1") -> None:
        self._render = render
        self._sock = socket.create_server((host, 0))
        self.host, self.port = self._sock.getsockname()[:2]
        self.frames_served = 0
        self._quit = threading.Event()
        self._thread = threading.Thread(target=self._accept, name="lab-camera", daemon=True)

    def start(self) -> CameraServer:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._quit.set()
        self._sock.close()
        self._thread.join(timeout=2.0)

    def _accept(self) -> None:
        while not self._quit.is_set():
            try:
                conn, _ = self._sock.accept()
            except OSError:
                return  # closed by stop()
            threading.Thread(
                target=self._serve, args=(conn,), name="lab-camera-client", daemon=True
            ).start()

    def _serve(self, conn: socket.socket) -> None:
        with conn, conn.makefile("rb") as reader:
            while not self._quit.is_set():
                line = reader.readline(MAX_REQUEST_BYTES)
                if not line:
                    return
                try:
                    header, payload = self._frame(line)
                except (ValueError, KeyError, TypeError) as e:
                    header, payload = {"error": f"{type(e).__name__}: {e}"}, b""
                try:
                    conn.sendall(json.dumps(header).encode() + b"\n" + payload)
                except OSError:
                    return
                if "error" in header and not line.endswith(b"\n"):
                    return  # an over-long line: the stream cannot be trusted any more

    def _frame(self, line: bytes) -> tuple[dict, bytes]:
        request = json.loads(line)
        camera = str(request["camera"])
        width, height = int(request["width"]), int(request["height"])
        if not (16 <= width <= MAX_SIDE and 16 <= height <= MAX_SIDE):
            raise ValueError(f"image size {width}x{height} is not in 16..{MAX_SIDE} a side")
        t0 = time.perf_counter()
        image = self._render(camera, width, height).result(timeout=30.0)
        self.frames_served += 1
        header = {
            "width": int(image.shape[1]),
            "height": int(image.shape[0]),
            "render_ms": (time.perf_counter() - t0) * 1000,
        }
        return header, np.ascontiguousarray(image, dtype=np.uint8).tobytes()
