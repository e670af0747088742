"""Inputs every section shares: seeded frames, their serial bytes, a capturing servo port.

The frames come from the project's synthetic pad model with its default
settings, over every pattern and grip level, so each number in the report
can be regenerated bit for bit from its seed.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from common.clocks.clock import now_ns
from common.devices.lifecycle import Device
from common.tactile.contract import N_GRIP_LEVELS, N_PATTERNS
from common.tactile.synthetic import GeneratorParams, SyntheticTactileModel, mirror_finger2
from operator_side.servos.base import ServoBus
from operator_side.servos.calibration import LinkGlideCalibration
from operator_side.servos.limits import check_goals
from operator_side.servos.sync_write import SyncWritePacket
from robot_side.tactile.serial_board import SerialTactileConfig, SerialTactileSensor
from robot_side.tactile.wire import encode

log = logging.getLogger(__name__)

#: the serial driver's default uniform calibration (SerialTactileConfig)
WIRE_GAIN_N_PER_COUNT = SerialTactileConfig().gain_n_per_count
#: goal position register of the STS servos (operator_side.servos.sts_registers)
GOAL_POSITION_ADDRESS = 42


@dataclass
class FrameSet:
    """Frames over every (pattern, grip level), ``repeats`` times each."""

    frames: np.ndarray  # (N, 2, 10, 10) float32 newtons, common view
    pattern: np.ndarray  # (N,) int64
    grip_level: np.ndarray  # (N,) int64
    seed: int

    def __len__(self) -> int:
        return len(self.frames)


def frame_set_of_at_least(n_frames: int, seed: int = 0) -> FrameSet:
    """The smallest whole number of :func:`frame_set` repeats holding ``n_frames``."""
    return frame_set(max(1, -(-n_frames // (N_PATTERNS * N_GRIP_LEVELS))), seed=seed)


def frame_set(repeats: int, seed: int = 0, params: GeneratorParams | None = None) -> FrameSet:
    """12 patterns x 31 grip levels x ``repeats``, one simulated sensor per seed.

    This is the set docs/tactile.md measured the rendering order on (default
    generator settings, the true pattern known for every frame).
    """
    model = SyntheticTactileModel(params or GeneratorParams(), seed=seed)
    rng = np.random.default_rng(seed)
    frames, patterns, levels = [], [], []
    for _ in range(repeats):
        for p in range(N_PATTERNS):
            for g in range(1, N_GRIP_LEVELS + 1):
                frames.append(model.frame(p, g, rng))
                patterns.append(p)
                levels.append(g)
    return FrameSet(
        np.stack(frames).astype(np.float32),
        np.array(patterns, dtype=np.int64),
        np.array(levels, dtype=np.int64),
        seed,
    )


def scan_bytes(frame: np.ndarray, seq: int) -> bytes:
    """Both pads of one scan as the board sends them (finger 2 in its own view)."""
    wire = mirror_finger2(np.asarray(frame, dtype=np.float64))
    counts = np.clip(np.rint(wire / WIRE_GAIN_N_PER_COUNT), 0, 0xFFFF).astype(np.uint16)
    return encode(0, seq, counts[0]) + encode(1, seq, counts[1])


def serial_sensor() -> SerialTactileSensor:
    """The real serial driver, never connected: its parser and frame code are fed directly."""
    return SerialTactileSensor(SerialTactileConfig(port="/dev/null"))


class CapturePort:
    """Stands in for scservo_sdk's PortHandler: keeps the bytes a write would send."""

    def __init__(self) -> None:
        self.is_using = False
        self.last_packet = b""
        self.packets = 0

    def clearPort(self) -> None:
        pass

    def writePort(self, packet: list[int]) -> int:
        self.last_packet = bytes(packet)
        self.packets += 1
        return len(packet)


class PacketBuilder:
    """The servo packet exactly as the Feetech driver builds it, minus the serial write.

    Goals are checked against the calibration (``limits.check_goals``, as
    every bus does) and laid into the goal sync-write packet
    (``SyncWritePacket``, byte for byte what scservo_sdk's ``GroupSyncWrite``
    builds), which the driver hands to the SDK's port handler.
    """

    def __init__(self, calibration: LinkGlideCalibration) -> None:
        self.calibration = calibration
        self.ids = tuple(int(i) for i in calibration.ids)
        self.packet = SyncWritePacket(self.ids, GOAL_POSITION_ADDRESS)
        self.port = CapturePort()

    def build(self, goals: Mapping[int, int]) -> bytes:
        return self.send(check_goals(self.calibration, goals))

    def send(self, checked: Mapping[int, int]) -> bytes:
        """Goals already checked (``ServoBus.write_goals`` does) into the packet."""
        self.port.clearPort()
        self.port.writePort(self.packet.build([checked[i] for i in self.ids]))
        return self.port.last_packet


class PacketServoBus(ServoBus):
    """A servo bus whose every write builds the real sync-write packet and keeps it.

    The operator node runs unchanged on it, so the end-to-end time ends where
    the Feetech driver would hand the bytes to the serial port.
    """

    Config = dict

    def __init__(self, calibration: LinkGlideCalibration | None = None) -> None:
        self.calibration = calibration or LinkGlideCalibration()
        self.builder = PacketBuilder(self.calibration)
        self._connected = False
        self.last_packet = b""
        self.last_write_ns = 0
        self.writes = 0

    def connect(self) -> None:
        self._connected = True

    def disconnect(self) -> None:
        self._connected = False

    @property
    def is_connected(self) -> bool:
        return self._connected

    def _write_goals(self, goals: dict[int, int]) -> None:
        self.last_packet = self.builder.send(goals)
        self.last_write_ns = now_ns()
        self.writes += 1

    def read_positions(self) -> dict[int, int]:
        return {}

    def set_torque(self, enabled: bool) -> None:
        pass

    def stats(self) -> dict[str, Any]:
        return {"writes": self.writes}

    def status(self) -> dict[str, Any]:
        return Device.status(self)
