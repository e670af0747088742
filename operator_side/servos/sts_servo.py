"""The fake STS bus's servos: their control tables, and positions that follow their goals."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from common.config.typed import param
from common.errors import ConfigError
from operator_side.servos.sts_registers import (
    BAUD_RATES,
    BROADCAST_ID,
    GOAL_POSITION,
    MODEL_NUMBER,
    MOVING,
    PRESENT_POSITION,
    PRESENT_SPEED,
    REG,
    TABLE_SIZE,
    TORQUE_ENABLE,
)

_READ_ONLY_FROM = PRESENT_POSITION.address  # the servo's own measurements


@dataclass
class FakeStsBusConfig:
    ids: tuple[int, ...] = param((1, 2, 3, 4, 5, 6), "servos on the bus")
    model_number: int = param(777, "answered at address 3 (777 = STS3215)")
    baudrate: int = param(1_000_000, "the servos' rate: a driver at another rate gets silence")
    speed_counts_per_s: float = param(
        4000.0, "how fast a present position follows its goal (STS3215: ~4500 at 7.4 V)"
    )
    start_counts: int = param(2048, "present position of every servo at power-up")
    voltage_decivolts: int = param(74, "present voltage, 0.1 V units")
    temperature_c: int = param(30, "present temperature")
    goal_log_size: int = param(100000, "goal writes remembered for inspection")
    link_dir: Path | None = param(None, "where the stable port symlink lives; unset = temp dir")

    def __post_init__(self) -> None:
        if not self.ids or any(not 0 <= i < BROADCAST_ID for i in self.ids):
            raise ConfigError(f"fake bus ids must be in 0..253, got {self.ids}")
        if len(set(self.ids)) != len(self.ids):
            raise ConfigError(f"fake bus ids must be unique, got {self.ids}")
        if not self.speed_counts_per_s > 0:
            raise ConfigError("speed_counts_per_s must be positive")
        if self.baudrate not in BAUD_RATES.values():
            raise ConfigError(f"baudrate {self.baudrate} is not an STS rate {BAUD_RATES}")


class FakeServo:
    """One servo: its control table, its present position, and how it fails."""

    def __init__(self, sid: int, cfg: FakeStsBusConfig) -> None:
        self.id = sid
        self.table = bytearray(TABLE_SIZE)
        self.silent = False
        self.error_bits = 0
        self.pending: tuple[int, bytes] | None = None  # REG_WRITE waiting for ACTION
        self.position = float(cfg.start_counts)
        self.put(MODEL_NUMBER.address, 2, cfg.model_number)
        self.put(REG["id"].address, 1, sid)
        baud_code = next(k for k, v in BAUD_RATES.items() if v == cfg.baudrate)
        self.put(REG["baud_rate"].address, 1, baud_code)
        self.put(REG["max_angle_limit"].address, 2, 4095)
        self.put(REG["max_torque"].address, 2, 1000)
        self.put(REG["torque_limit"].address, 2, 1000)
        self.put(GOAL_POSITION.address, 2, cfg.start_counts)
        self.put(PRESENT_POSITION.address, 2, cfg.start_counts)
        self.put(REG["present_voltage"].address, 1, cfg.voltage_decivolts)
        self.put(REG["present_temperature"].address, 1, cfg.temperature_c)

    def put(self, address: int, size: int, value: int) -> None:
        self.table[address : address + size] = int(value).to_bytes(size, "little")

    def get(self, address: int, size: int) -> int:
        return int.from_bytes(self.table[address : address + size], "little")

    @property
    def torque(self) -> bool:
        return bool(self.table[TORQUE_ENABLE.address])

    @property
    def goal(self) -> int:
        return self.get(GOAL_POSITION.address, 2)

    def write(self, address: int, data: bytes) -> None:
        """Apply a write as the servo would: its own measurements stay its own."""
        was_on = self.torque
        for k, b in enumerate(data):
            a = address + k
            if a < min(_READ_ONLY_FROM, TABLE_SIZE):
                self.table[a] = b
        if was_on and not self.torque:
            self.put(MOVING.address, 1, 0)
            self.put(PRESENT_SPEED.address, 2, 0)

    def advance(self, dt_s: float, speed: float) -> None:
        if not self.torque:
            return
        goal = float(self.goal)
        step = speed * dt_s
        delta = goal - self.position
        if abs(delta) <= step:
            self.position = goal
            moving, velocity = 0, 0
        else:
            self.position += step if delta > 0 else -step
            moving, velocity = 1, int(speed)
        self.put(PRESENT_POSITION.address, 2, round(self.position) & 0xFFFF)
        # STS speed: magnitude with bit 15 as the sign.
        self.put(PRESENT_SPEED.address, 2, velocity | (0x8000 if delta < 0 and velocity else 0))
        self.put(MOVING.address, 1, moving)
