"""The lab world in a child process, asked questions over its stdin/stdout.

A process because ur-rtde's constructors hold the GIL while they wait for the
controller (a simulator in the same interpreter could never answer), and
because the physics should have its own core. One JSON request per line,
one JSON answer per line; the child exits when its stdin closes.

Camera frames on demand: ``LabWorldProcess.camera_frame(camera, width,
height)`` returns one RGB image (numpy, uint8, height x width x 3) rendered
at that moment; nothing is rendered unless somebody asks. Cameras:
``camera_names()`` (``overview`` and ``wrist``).
"""

from __future__ import annotations

import base64
import contextlib
import json
import logging
import os
import select
import subprocess
import sys
import threading
from typing import IO, Any

import numpy as np

from common.config import to_dict
from common.errors import DeviceError, DeviceTimeoutError
from robot_side.lab.config import LabWorldConfig

log = logging.getLogger(__name__)


def serve_stdio(server: Any, stdin: IO[str], stdout: IO[str]) -> None:
    """The child's side: answer requests until stdin closes or "stop" arrives."""
    from robot_side.lab.server import REMOTE_METHODS

    def reply(obj: dict[str, Any]) -> None:
        stdout.write(json.dumps(obj) + "\n")
        stdout.flush()

    reply({"ready": server.addresses()})
    try:
        for line in stdin:
            req = json.loads(line)
            method, args = req.get("method"), req.get("args", [])
            if method == "stop":
                break
            try:
                if method not in REMOTE_METHODS:
                    raise AttributeError(f"the lab has no remote method {method!r}")
                reply({"ok": getattr(server, method)(*args)})
            except Exception as e:  # reported to the parent, which raises it
                reply({"error": f"{type(e).__name__}: {e}"})
    finally:
        server.stop()
    with contextlib.suppress(OSError):
        reply({"ok": None})


class LabWorldProcess:
    """Start with :meth:`start`; ``addresses`` then says where each simulator listens."""

    def __init__(self, config: LabWorldConfig | None = None, log_level: int = logging.WARNING):
        self.config = config or LabWorldConfig()
        self.log_level = log_level
        self.addresses: dict[str, Any] = {}
        self._proc: subprocess.Popen[str] | None = None
        self._lock = threading.Lock()

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def start(self, timeout_s: float = 30.0) -> LabWorldProcess:
        cmd = [
            sys.executable,
            "-m",
            "robot_side.lab",
            "--stdio",
            "--config-json",
            json.dumps(to_dict(self.config)),
            "--log-level",
            str(self.log_level),
        ]
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self._proc = subprocess.Popen(
            cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env
        )
        try:
            msg = self._read(timeout_s, "start")
        except DeviceError:
            self.stop()
            raise
        if "ready" not in msg:
            self.stop()
            raise DeviceError(f"lab world failed to start: {msg.get('error', msg)}")
        self.addresses = msg["ready"]
        log.info(
            "lab world process %d: UR on %s, gripper on %s:%s, pads on %s",
            self._proc.pid,
            self.addresses["ur_host"],
            self.addresses["gripper_host"],
            self.addresses["gripper_port"],
            self.addresses["tactile_port"],
        )
        return self

    def _read(self, timeout_s: float, what: str) -> dict[str, Any]:
        proc = self._proc
        assert proc is not None and proc.stdout is not None
        ready, _, _ = select.select([proc.stdout], [], [], timeout_s)
        if not ready:
            raise DeviceTimeoutError(f"lab world did not answer {what} in {timeout_s:.0f} s")
        line = proc.stdout.readline()
        if not line:
            raise DeviceError(
                f"lab world process exited during {what} (code {proc.poll()}); see its stderr"
            )
        return json.loads(line)

    def call(self, method: str, *args: Any, timeout_s: float = 10.0) -> Any:
        with self._lock:
            proc = self._proc
            if proc is None or proc.stdin is None or not self.running:
                raise DeviceError("lab world process is not running: call start() first")
            proc.stdin.write(json.dumps({"method": method, "args": list(args)}) + "\n")
            proc.stdin.flush()
            msg = self._read(timeout_s, method)
        if "error" in msg:
            raise DeviceError(f"lab world {method}: {msg['error']}")
        return msg.get("ok")

    # -- the API for tests, tools and the dashboard ----------------------------------------

    def stats(self) -> dict[str, Any]:
        """Physics step cost, real-time factor, protective stops, the board's counters."""
        return self.call("stats")

    def taxel_forces(self) -> np.ndarray:
        """The engine's true (2, 10, 10) taxel forces now, before the pad model."""
        return np.asarray(self.call("taxel_forces"))

    def grasp(self) -> dict[str, Any]:
        """Ground truth: which pipette the pads press, its pattern, tilt and offset."""
        return self.call("grasp")

    def camera_names(self) -> list[str]:
        return self.call("camera_names")

    def camera_frame(
        self, camera: str = "overview", width: int = 320, height: int = 240
    ) -> np.ndarray:
        """One RGB image rendered now (headless EGL by default: ~100 ms for 320x240)."""
        msg = self.call("camera_frame", camera, width, height, timeout_s=30.0)
        raw = base64.b64decode(msg["rgb"])
        return np.frombuffer(raw, dtype=np.uint8).reshape(msg["height"], msg["width"], 3)

    def stop(self, timeout_s: float = 5.0) -> None:
        proc, self._proc = self._proc, None
        if proc is None:
            return
        try:
            if proc.poll() is None and proc.stdin is not None:
                proc.stdin.write(json.dumps({"method": "stop"}) + "\n")
                proc.stdin.flush()
        except OSError as e:
            log.debug("lab world stop: %s", e)
        for f in (proc.stdin, proc.stdout):
            if f is not None:
                with contextlib.suppress(OSError):
                    f.close()
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=2)

    def __enter__(self) -> LabWorldProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
