"""A gripper that only remembers what it was told: for tests, benches and the demo.

The real ``Gripper`` checks (byte ranges, grip levels, activation) run
unchanged; the registers live in memory and the fingers arrive at once,
stopping at the requested position (object status "at position").
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass
from typing import Any

from common.config.typed import param
from common.errors import DeviceAlreadyConnectedError
from robot_side.gripper.base import (
    ActivationStatus,
    GripLevels,
    Gripper,
    GripperState,
    ObjectStatus,
)


@dataclass
class MemoryGripperConfig:
    activate_on_connect: bool = param(True, "activate at connect, as the real drivers do")
    levels: GripLevels = param(GripLevels(), "grip level 1..31 -> position and force")
    max_records: int = param(100000, "oldest commands are forgotten beyond this")

    def __post_init__(self) -> None:
        if self.max_records < 1:
            raise ValueError(f"max_records must be at least 1, not {self.max_records}")


class MemoryGripper(Gripper):
    """Records each command as (position, speed, force, go); activation is instant."""

    Config = MemoryGripperConfig
    simulated = True

    def __init__(self, config: MemoryGripperConfig | None = None) -> None:
        self.config = config or MemoryGripperConfig()
        super().__init__(self.config.levels)
        self._connected = False
        self._active = False
        self._position = 0
        self._lock = threading.Lock()
        self._commands: deque[tuple[int, int, int, bool]] = deque(maxlen=self.config.max_records)

    def connect(self) -> None:
        if self._connected:
            raise DeviceAlreadyConnectedError("MemoryGripper is already connected")
        self._connected = True
        if self.config.activate_on_connect:
            self.activate()

    def disconnect(self) -> None:
        self._connected = False

    @property
    def is_connected(self) -> bool:
        return self._connected

    def _write_activate(self) -> None:
        self._active = True

    def _write_command(self, position: int, speed: int, force: int, go: bool) -> None:
        with self._lock:
            self._commands.append((position, speed, force, go))
        self._position = position

    def _read_state(self) -> GripperState:
        return GripperState(
            activation=ActivationStatus.ACTIVE if self._active else ActivationStatus.RESET,
            goto=True,
            object_status=ObjectStatus.AT_POSITION,
            fault=0,
            requested_position=self._position,
            position=self._position,
        )

    @property
    def commands(self) -> list[tuple[int, int, int, bool]]:
        """(position, speed, force, go) of every command, oldest first."""
        with self._lock:
            return list(self._commands)

    def status(self) -> dict[str, Any]:
        out = super().status()
        with self._lock:
            out["commands"] = len(self._commands)
        return out
