"""The dashboard server on 29999: the text commands ur-rtde sends, one line each way.

PolyscopeVersion, ``get serial number``, robotmode, safetystatus, is in
remote control, play, stop, power on, brake release, ...: what ur-rtde's
dashboard client asks, answered from the simulated controller's state.
"""

from __future__ import annotations

import contextlib
import logging
import socket
from typing import Any

from robot_side.arm.sim.controller import SAFETY_MODE_NORMAL, Controller
from robot_side.arm.sim.script import ControlScript

log = logging.getLogger(__name__)
wire_log = logging.getLogger("robot_side.arm.sim.wire")


class DashboardServer:
    """Answers the dashboard's commands; ``stop`` ends the program, ``power`` and
    ``unlock protective stop`` change the controller's state."""

    def __init__(self, controller: Controller, script: ControlScript) -> None:
        self.controller = controller
        self.script = script

    def serve(self, sock: socket.socket, peer: Any) -> None:
        """One dashboard client, until it says ``quit`` or goes."""
        try:
            sock.sendall(b"Connected: Universal Robots Dashboard Server\n")
            f = sock.makefile("rb")
            for raw in f:
                line = raw.decode(errors="replace").strip()
                reply = self.reply(line)
                wire_log.debug("dashboard <- %r -> %r", line, reply)
                sock.sendall(reply.encode() + b"\n")
                if line == "quit":
                    break
        except OSError:
            pass
        finally:
            with contextlib.suppress(OSError):
                sock.close()

    def reply(self, line: str) -> str:
        cmd = line.lower()
        controller, config = self.controller, self.controller.config
        with controller.lock:
            normal = controller.safety_mode == SAFETY_MODE_NORMAL
            if cmd == "polyscopeversion":
                return config.polyscope_version
            if cmd == "version":
                return ".".join(str(v) for v in config.controller_version)
            if cmd == "get serial number":
                return config.serial_number
            if cmd == "get robot model":
                return "UR3"
            if cmd == "robotmode":
                return "Robotmode: RUNNING" if controller.powered else "Robotmode: POWER_OFF"
            if cmd == "safetystatus":
                return "Safetystatus: NORMAL" if normal else "Safetystatus: PROTECTIVE_STOP"
            if cmd == "safetymode":
                return "Safetymode: NORMAL" if normal else "Safetymode: PROTECTIVE_STOP"
            if cmd == "is in remote control":
                return "true"
            if cmd == "running":
                return f"Program running: {'true' if self.script.program_running else 'false'}"
            if cmd == "programstate":
                return (
                    "PLAYING rtde_control" if self.script.program_running else "STOPPED <unnamed>"
                )
            if cmd == "play":
                return "Starting program"
            if cmd == "stop":
                self.script.stop_program("stop on the dashboard")
                return "Stopped"
            if cmd == "pause":
                return "Pausing program"
            if cmd == "power on":
                controller.powered = True
                return "Powering on"
            if cmd == "power off":
                controller.powered = False
                return "Powering off"
            if cmd == "brake release":
                return "Brake releasing"
            if cmd == "unlock protective stop":
                controller.safety_mode = SAFETY_MODE_NORMAL
                return "Protective stop releasing"
            if cmd == "close popup":
                return "closing popup"
            if cmd == "close safety popup":
                return "closing safety popup"
            if cmd == "isprogramsaved":
                return "true <unnamed>"
            if cmd == "get loaded program":
                return "No program loaded"
            if cmd == "quit":
                return "Disconnected"
            if cmd.startswith("popup") or cmd.startswith("addtolog"):
                return "Added log message" if cmd.startswith("addtolog") else "showing popup"
        log.warning("dashboard command %r is not simulated", line)
        return f"could not understand: '{line}'"
