"""An arm that only remembers what it was told: for tests, benches and the demo.

The real ``Arm`` safety layer (speed caps, workspace box, the jog deadman)
runs unchanged on it; the "driver" keeps every jog, move and stop with its
time. The TCP is an ideal one: a move arrives at once, a jog does not move
it (the TCP stays where the last move put it), so what a test sees is what
the safety layer decided, not a trajectory.
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from common.clocks.clock import now_ns
from common.config.typed import param
from common.errors import DeviceAlreadyConnectedError
from robot_side.arm.base import Arm, ArmLimits, as_vector6


@dataclass
class MemoryArmConfig:
    start_pose: tuple[float, float, float, float, float, float] = param(
        (0.0, 0.0, 0.3, 0.0, 3.14, 0.0), "TCP pose at connect (m, rotation vector): tool down"
    )
    limits: ArmLimits = param(ArmLimits(), "workspace box, speed caps and the jog deadman")
    max_records: int = param(100000, "oldest jogs and moves are forgotten beyond this")

    def __post_init__(self) -> None:
        if self.max_records < 1:
            raise ValueError(f"max_records must be at least 1, not {self.max_records}")


class MemoryArm(Arm):
    """Records each jog (the velocity the safety layer let through), move and stop."""

    Config = MemoryArmConfig
    simulated = True

    def __init__(self, config: MemoryArmConfig | None = None) -> None:
        self.config = config or MemoryArmConfig()
        super().__init__(self.config.limits)
        self._connected = False
        self._pose = as_vector6(self.config.start_pose, "start_pose")
        self._records_lock = threading.Lock()
        self._jogs: deque[tuple[int, np.ndarray]] = deque(maxlen=self.config.max_records)
        self._moves: deque[tuple[int, np.ndarray, float]] = deque(maxlen=self.config.max_records)
        self._stop_times: list[int] = []

    # -- lifecycle -----------------------------------------------------------

    def connect(self) -> None:
        if self._connected:
            raise DeviceAlreadyConnectedError("MemoryArm is already connected")
        self._connected = True
        self._start_deadman()

    def disconnect(self) -> None:
        self._stop_deadman()
        if self._connected:
            self.stop()
        self._connected = False

    @property
    def is_connected(self) -> bool:
        return self._connected

    # -- the "driver" --------------------------------------------------------

    def _read_tcp_pose(self) -> np.ndarray:
        return self._pose.copy()

    def _read_joints(self) -> np.ndarray:
        return np.zeros(6)

    def _send_jog(self, velocity: np.ndarray) -> None:
        with self._records_lock:
            self._jogs.append((now_ns(), np.array(velocity, dtype=float)))

    def _send_move(self, pose: np.ndarray, speed: float) -> None:
        with self._records_lock:
            self._moves.append((now_ns(), np.array(pose, dtype=float), speed))
        self._pose = np.array(pose, dtype=float)

    def _move_finished(self) -> bool:
        return True

    def _send_stop(self) -> None:
        with self._records_lock:
            self._stop_times.append(now_ns())

    # -- inspection (tests, demo) --------------------------------------------

    @property
    def sent_jogs(self) -> list[np.ndarray]:
        """Every velocity the safety layer sent, oldest first."""
        with self._records_lock:
            return [v for _, v in self._jogs]

    @property
    def jog_times_ns(self) -> list[int]:
        with self._records_lock:
            return [t for t, _ in self._jogs]

    @property
    def moves(self) -> list[tuple[np.ndarray, float]]:
        """(target pose, speed) of every move, oldest first."""
        with self._records_lock:
            return [(p, s) for _, p, s in self._moves]

    @property
    def stop_times_ns(self) -> list[int]:
        with self._records_lock:
            return list(self._stop_times)

    @property
    def stops(self) -> int:
        with self._records_lock:
            return len(self._stop_times)

    def status(self) -> dict[str, Any]:
        out = super().status()
        with self._records_lock:
            out.update(jogs=len(self._jogs), moves=len(self._moves), stops=len(self._stop_times))
        return out
