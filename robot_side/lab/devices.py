"""The lab kinds: the real drivers against the simulators a shared world process feeds.

``kind = "lab"`` for ``[robot.tactile]``, ``[robot.gripper]`` and
``[robot.arm]``: each is the unchanged real driver (serial board, URCap
socket, ur-rtde) pointed at the world's simulator. The three attach to one
world process per ``world_config`` in this process (started by the first to
connect, stopped when the last disconnects), so closing the gripper presses
the pipette on the same pads the tactile driver reads.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from common.config import from_dict, load_toml, param
from robot_side.arm.ur_rtde import URArm, URArmConfig
from robot_side.gripper.urcap_socket import RobotiqSocketConfig, RobotiqSocketGripper
from robot_side.lab.config import LabWorldConfig
from robot_side.lab.process import LabWorldProcess
from robot_side.tactile.board_calibration import BoardCalibration
from robot_side.tactile.serial_board import SerialTactileConfig, SerialTactileSensor

log = logging.getLogger(__name__)

_worlds: dict[str, tuple[LabWorldProcess, int]] = {}
_worlds_lock = threading.Lock()


def world_config_from(path: Path | None) -> LabWorldConfig:
    """The shipped default world, or the ``LabWorldConfig`` fields in a TOML file."""
    if path is None:
        return LabWorldConfig()
    return from_dict(LabWorldConfig, load_toml(path), where=str(path))


def attach_world(path: Path | None) -> LabWorldProcess:
    """The running world for ``path`` in this process, started on first use."""
    key = str(path.resolve()) if path is not None else "<default>"
    with _worlds_lock:
        if key in _worlds:
            world, users = _worlds[key]
            _worlds[key] = (world, users + 1)
            return world
        world = LabWorldProcess(world_config_from(path)).start()
        _worlds[key] = (world, 1)
        return world


def detach_world(world: LabWorldProcess) -> None:
    with _worlds_lock:
        for key, (w, users) in list(_worlds.items()):
            if w is world:
                if users > 1:
                    _worlds[key] = (w, users - 1)
                else:
                    del _worlds[key]
                    w.stop()
                return


WORLD_CONFIG_WHY = "the world's settings (LabWorldConfig TOML); unset = the shipped lab"


@dataclass
class LabTactileConfig:
    world_config: Path | None = param(None, WORLD_CONFIG_WHY)
    driver: SerialTactileConfig = param(
        SerialTactileConfig(), "the real serial driver; its port is set to the world's board"
    )


class LabTactileSensor(SerialTactileSensor):
    """The real serial driver reading the world's tactile board on its pty."""

    Config = LabTactileConfig  # type: ignore[assignment]
    simulated = True

    def __init__(self, config: LabTactileConfig | None = None) -> None:
        self.lab_config = config or LabTactileConfig()
        super().__init__(self.lab_config.driver)
        self.world: LabWorldProcess | None = None

    def connect(self) -> None:
        self.world = attach_world(self.lab_config.world_config)
        a = self.world.addresses
        try:
            self.config = dataclasses.replace(self.config, port=a["tactile_port"])
            if self.config.calibration_file is None:
                cal = BoardCalibration(np.asarray(a["tactile_zero"]), np.asarray(a["tactile_gain"]))
                self.set_calibration(cal)
            super().connect()
        except BaseException:
            detach_world(self.world)
            self.world = None
            raise

    def disconnect(self) -> None:
        try:
            super().disconnect()
        finally:
            if self.world is not None:
                detach_world(self.world)
                self.world = None


@dataclass
class LabGripperConfig(RobotiqSocketConfig):
    host: str = param("auto", "ignored: the world's gripper simulator is used")
    port: int = param(0, "ignored: the world's gripper simulator is used")
    world_config: Path | None = param(None, WORLD_CONFIG_WHY)


class LabGripper(RobotiqSocketGripper):
    """The real URCap socket driver against the world's 2F-85."""

    Config = LabGripperConfig
    simulated = True

    def __init__(self, config: LabGripperConfig | None = None) -> None:
        super().__init__(config or LabGripperConfig())
        self.world: LabWorldProcess | None = None

    def connect(self) -> None:
        assert isinstance(self.config, LabGripperConfig)
        self.world = attach_world(self.config.world_config)
        self.config.host = self.world.addresses["gripper_host"]
        self.config.port = self.world.addresses["gripper_port"]
        try:
            super().connect()
        except BaseException:
            detach_world(self.world)
            self.world = None
            raise

    def disconnect(self) -> None:
        try:
            super().disconnect()
        finally:
            if self.world is not None:
                detach_world(self.world)
                self.world = None


@dataclass
class LabArmConfig(URArmConfig):
    host: str = param("auto", "ignored: the world's UR controller simulator is used")
    stale_after_s: float = param(
        0.5, "the simulated controller shares its process with the physics: allow it a stall"
    )
    world_config: Path | None = param(None, WORLD_CONFIG_WHY)


class LabArm(URArm):
    """The real ur-rtde driver against the world's UR3e controller."""

    Config = LabArmConfig
    simulated = True

    def __init__(self, config: LabArmConfig | None = None) -> None:
        super().__init__(config or LabArmConfig())
        self.world: LabWorldProcess | None = None

    def connect(self) -> None:
        assert isinstance(self.config, LabArmConfig)
        self.world = attach_world(self.config.world_config)
        self.config.host = self.world.addresses["ur_host"]
        try:
            super().connect()
        except BaseException:
            detach_world(self.world)
            self.world = None
            raise

    def disconnect(self) -> None:
        try:
            super().disconnect()
        finally:
            if self.world is not None:
                detach_world(self.world)
                self.world = None
