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
import logging
from typing import IO, Any

import numpy as np

from common.devices.lifecycle import SIMULATED_HARDWARE_NICE
from robot_side.devices.stdio_child import StdioChild
from robot_side.devices.stdio_child import serve_stdio as serve_child
from robot_side.lab.config import LabWorldConfig

log = logging.getLogger(__name__)


def serve_stdio(server: Any, stdin: IO[str], stdout: IO[str]) -> None:
    """The child's side: answer requests until stdin closes or "stop" arrives."""
    from robot_side.lab.server import REMOTE_METHODS

    serve_child(server, REMOTE_METHODS, server.addresses(), stdin, stdout, on_exit=server.stop)


class LabWorldProcess(StdioChild):
    """Start with :meth:`start`; ``addresses`` then says where each simulator listens."""

    def __init__(self, config: LabWorldConfig | None = None, log_level: int = logging.WARNING):
        # the world's physics and the controllers in it are the lab's hardware
        super().__init__(
            "robot_side.lab",
            config or LabWorldConfig(),
            "lab world",
            log_level,
            nice=SIMULATED_HARDWARE_NICE,
        )
        self.addresses: dict[str, Any] = {}

    def start(self, timeout_s: float = 30.0) -> LabWorldProcess:
        self.addresses = self.start_child(timeout_s)
        log.info(
            "lab world process %s: UR on %s, gripper on %s:%s, pads on %s",
            self.pid,
            self.addresses["ur_host"],
            self.addresses["gripper_host"],
            self.addresses["gripper_port"],
            self.addresses["tactile_port"],
        )
        return self

    def call(self, method: str, *args: Any, timeout_s: float = 10.0) -> Any:
        return super().call(method, *args, timeout_s=timeout_s)

    # -- the API for tests, tools and the dashboard ----------------------------------------

    def stats(self) -> dict[str, Any]:
        """Physics step cost, real-time factor, protective stops, the board's counters."""
        return self.call("stats")

    def taxel_forces(self) -> np.ndarray:
        """The engine's true ``FRAME_SHAPE`` taxel forces now, before the pad model."""
        return np.asarray(self.call("taxel_forces"))

    def grasp(self) -> dict[str, Any]:
        """Ground truth: which pipette the pads press, its pattern, tilt and offset."""
        return self.call("grasp")

    def reset_trial(self, pipette: int, x_m: float, tilt_deg: float) -> dict[str, Any]:
        """A new trial (simulation only): arm home at rest, the pipette re-placed in the rack."""
        return self.call("reset_trial", pipette, x_m, tilt_deg)

    def pipette_lift_mm(self, pipette: int) -> float:
        """How far the pipette has been drawn up out of its rack hole (mm)."""
        return float(self.call("pipette_lift_mm", pipette))

    def camera_names(self) -> list[str]:
        return self.call("camera_names")

    def camera_frame(
        self, camera: str = "overview", width: int = 320, height: int = 240
    ) -> np.ndarray:
        """One RGB image rendered now (headless EGL by default: ~100 ms for 320x240)."""
        msg = self.call("camera_frame", camera, width, height, timeout_s=30.0)
        raw = base64.b64decode(msg["rgb"])
        return np.frombuffer(raw, dtype=np.uint8).reshape(msg["height"], msg["width"], 3)

    def __enter__(self) -> LabWorldProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
