"""A servo bus that keeps in memory what it was told: for tests and the demo.

The operator node runs unchanged on it: every ``write_goals`` is kept with its
timestamp, present positions are the last goals (an ideal, instantaneous
servo), and counts outside the calibrated limits are refused exactly as the
real Feetech driver refuses them, so a test that passes here cannot hide a
limit violation that the hardware would have received.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from common.clocks.clock import now_ns
from common.config.typed import param
from common.devices.lifecycle import Device
from common.errors import DeviceAlreadyConnectedError
from operator_side.servos.base import ServoBus
from operator_side.servos.calibration import LinkGlideCalibration, load_calibration

log = logging.getLogger(__name__)


@dataclass
class InMemoryServoBusConfig:
    calibration: LinkGlideCalibration = param(
        LinkGlideCalibration(), "limits to enforce, used when calibration_file is unset"
    )
    calibration_file: Path | None = param(
        None, "TOML from `deepxpalm calibrate`; overrides the inline calibration"
    )
    max_records: int = param(10000, "oldest writes are forgotten beyond this (bounded memory)")

    def __post_init__(self) -> None:
        if self.max_records < 1:
            raise ValueError(f"max_records must be at least 1, not {self.max_records}")


@dataclass(frozen=True, slots=True)
class GoalRecord:
    t_ns: int  # monotonic clock, when write_goals was called
    goals: dict[int, int]  # servo id -> counts, exactly what was "sent"


class InMemoryServoBus(ServoBus):
    """Records each sync write; refuses out-of-limit counts like the real bus."""

    Config = InMemoryServoBusConfig
    simulated = True

    def __init__(self, config: InMemoryServoBusConfig | None = None) -> None:
        self.config = config or InMemoryServoBusConfig()
        self._lock = threading.Lock()
        self._connected = False
        self._calibration: LinkGlideCalibration | None = None
        self._records: deque[GoalRecord] = deque(maxlen=self.config.max_records)
        self._positions: dict[int, int] = {}
        self._torque = False
        self._writes = 0

    # -- lifecycle -----------------------------------------------------------

    def connect(self) -> None:
        if self._connected:
            raise DeviceAlreadyConnectedError("InMemoryServoBus is already connected")
        cfg = self.config
        self._calibration = (
            load_calibration(cfg.calibration_file) if cfg.calibration_file else cfg.calibration
        )
        # Start at each servo's zero (clipped), as a powered-up servo holds a pose.
        self._positions = {
            s.id: min(max(s.zero_counts, s.min_counts), s.max_counts)
            for s in self._calibration.servos
        }
        self._torque = True
        self._connected = True

    def disconnect(self) -> None:
        self._torque = False
        self._connected = False

    @property
    def is_connected(self) -> bool:
        return self._connected

    # -- ServoBus ------------------------------------------------------------

    def _write_goals(self, checked: dict[int, int]) -> None:
        with self._lock:
            self._records.append(GoalRecord(now_ns(), checked))
            self._positions.update(checked)
            self._writes += 1

    def read_positions(self) -> dict[int, int]:
        self.require_connected()
        with self._lock:
            return dict(self._positions)

    def set_torque(self, enabled: bool) -> None:
        self.require_connected()
        self._torque = bool(enabled)

    # -- inspection (tests, demo) --------------------------------------------

    @property
    def records(self) -> list[GoalRecord]:
        """A copy of the kept writes, oldest first."""
        with self._lock:
            return list(self._records)

    @property
    def torque_enabled(self) -> bool:
        return self._torque

    @property
    def calibration(self) -> LinkGlideCalibration | None:
        return self._calibration

    def clear(self) -> None:
        with self._lock:
            self._records.clear()

    def status(self) -> dict[str, Any]:
        s = Device.status(self)
        with self._lock:
            s.update(writes=self._writes, refused=self.refused_writes, torque=self._torque)
        return s
