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
import json
import logging
import threading
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from common.config.typed import from_dict, load_toml, param
from common.errors import ConfigError
from robot_side.arm.process import InOwnProcess
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


class RunningWorld:
    """A world another process started: only where its simulators listen, read from a file.

    ``python -m robot_side.lab --addresses-file F`` (or a bench harness holding
    a ``LabWorldProcess``) writes the file; this process never stops that world.
    """

    def __init__(self, path: Path) -> None:
        try:
            self.addresses = json.loads(Path(path).read_text())
        except (OSError, ValueError) as e:
            raise ConfigError(
                f"running_world {path}: cannot read the world's addresses: {e}"
            ) from e
        missing = {"ur_host", "gripper_host", "gripper_port", "tactile_port"} - set(self.addresses)
        if missing:
            raise ConfigError(f"running_world {path}: no {sorted(missing)} in the addresses")

    def stop(self) -> None:
        """Nothing: the world belongs to the process that started it."""


def attach_world(path: Path | None, running: Path | None = None) -> LabWorldProcess | RunningWorld:
    """The world for ``path`` in this process, started on first use; or a running one's."""
    if running is not None:
        path, key = None, f"running:{Path(running).resolve()}"
    else:
        key = str(path.resolve()) if path is not None else "<default>"
    with _worlds_lock:
        if key in _worlds:
            world, users = _worlds[key]
            _worlds[key] = (world, users + 1)
            return world
        world = (
            RunningWorld(running)
            if running is not None
            else LabWorldProcess(world_config_from(path)).start()
        )
        _worlds[key] = (world, 1)
        return world


def detach_world(world: LabWorldProcess | RunningWorld) -> None:
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
RUNNING_WORLD_WHY = (
    "a world another process runs: its addresses JSON (python -m robot_side.lab "
    "--addresses-file); unset = start one here from world_config"
)


class OnTheWorld(ABC):
    """A real driver's ``connect``/``disconnect`` around the shared world process.

    Mixed in before the driver class: ``connect`` attaches to the world,
    lets the kind point its driver at the world's simulator
    (:meth:`point_at`), then connects the driver; a failure or a
    ``disconnect`` detaches again, so the last user stops the world.
    """

    world: LabWorldProcess | RunningWorld | None = None

    def world_config_path(self) -> Path | None:
        return self.config.world_config  # type: ignore[attr-defined]

    def running_world_path(self) -> Path | None:
        return self.config.running_world  # type: ignore[attr-defined]

    @abstractmethod
    def point_at(self, addresses: dict) -> None:
        """Set the driver's port or host from where the world's simulators listen."""

    def find_device(self) -> None:
        """Attach to the world and point the driver at its simulator (an arm process's
        driver, in a process of its own, is pointed by its ``ArmProcess``)."""
        self.world = attach_world(self.world_config_path(), self.running_world_path())
        try:
            self.point_at(self.world.addresses)
        except BaseException:
            self.release_device()
            raise

    def release_device(self) -> None:
        if self.world is not None:
            detach_world(self.world)
            self.world = None

    def connect(self) -> None:
        self.find_device()
        try:
            super().connect()  # type: ignore[misc]
        except BaseException:
            self.release_device()
            raise

    def disconnect(self) -> None:
        try:
            super().disconnect()  # type: ignore[misc]
        finally:
            if self.world is not None:
                detach_world(self.world)
                self.world = None


@dataclass
class LabTactileConfig:
    world_config: Path | None = param(None, WORLD_CONFIG_WHY)
    running_world: Path | None = param(None, RUNNING_WORLD_WHY)
    driver: SerialTactileConfig = param(
        SerialTactileConfig(), "the real serial driver; its port is set to the world's board"
    )


class LabTactileSensor(OnTheWorld, SerialTactileSensor):
    """The real serial driver reading the world's tactile board on its pty."""

    Config = LabTactileConfig  # type: ignore[assignment]
    simulated = True

    def __init__(self, config: LabTactileConfig | None = None) -> None:
        self.lab_config = config or LabTactileConfig()
        super().__init__(self.lab_config.driver)

    def world_config_path(self) -> Path | None:
        return self.lab_config.world_config

    def running_world_path(self) -> Path | None:
        return self.lab_config.running_world

    def point_at(self, addresses: dict) -> None:
        self.config = dataclasses.replace(self.config, port=addresses["tactile_port"])
        if self.config.calibration_file is None:
            zero, gain = addresses["tactile_zero"], addresses["tactile_gain"]
            self.set_calibration(BoardCalibration(np.asarray(zero), np.asarray(gain)))


@dataclass
class LabGripperConfig(RobotiqSocketConfig):
    host: str = param("auto", "ignored: the world's gripper simulator is used")
    port: int = param(0, "ignored: the world's gripper simulator is used")
    reply_timeout_s: float = param(
        3.0,
        "the world's gripper simulator shares its process with the physics and the cameras' "
        "renderer: allow it a stall (a world starting on a loaded machine answered over 1 s late)",
    )
    world_config: Path | None = param(None, WORLD_CONFIG_WHY)
    running_world: Path | None = param(None, RUNNING_WORLD_WHY)


class LabGripper(OnTheWorld, RobotiqSocketGripper):
    """The real URCap socket driver against the world's 2F-85."""

    Config = LabGripperConfig
    simulated = True

    def __init__(self, config: LabGripperConfig | None = None) -> None:
        super().__init__(config or LabGripperConfig())

    def point_at(self, addresses: dict) -> None:
        self.config.host = addresses["gripper_host"]
        self.config.port = addresses["gripper_port"]


@dataclass
class LabArmConfig(URArmConfig):
    host: str = param("auto", "ignored: the world's UR controller simulator is used")
    stale_after_s: float = param(
        0.5, "the simulated controller shares its process with the physics: allow it a stall"
    )
    world_config: Path | None = param(None, WORLD_CONFIG_WHY)
    running_world: Path | None = param(None, RUNNING_WORLD_WHY)


class LabArm(OnTheWorld, URArm):
    """The real ur-rtde driver against the world's UR3e controller."""

    Config = LabArmConfig
    simulated = True

    def __init__(self, config: LabArmConfig | None = None) -> None:
        super().__init__(config or LabArmConfig())

    def point_at(self, addresses: dict) -> None:
        self.config.host = addresses["ur_host"]


class LabArmKind(InOwnProcess):
    """Kind "lab": the world in the node, ``URArm`` in its arm process unless
    ``own_process = false``."""

    driver = LabArm
    Config = LabArmConfig
