"""The serial tactile board driver's settings: the port, staleness, reconnects, calibration."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from common.config.typed import param
from common.tactile.contract import SATURATION_N
from robot_side.tactile.wire import DEFAULT_BAUD


@dataclass
class SerialTactileConfig:
    port: str = param(
        "/dev/ttyACM0", "the board's serial port; prefer its stable /dev/serial/by-id/... name"
    )
    baudrate: int = param(
        DEFAULT_BAUD, "must match the board firmware; 921600 carries 120 Hz at 55 %"
    )
    max_age_ms: float = param(
        50.0, "read_latest() default: a newer frame is due every 8.3 ms, so 6 missed = stale"
    )
    connect_timeout_s: float = param(
        1.0, "connect() waits this long for the first good frame before it names the problem"
    )
    read_timeout_s: float = param(
        0.02, "longest a read blocks: how fast the reader notices stop() and a silent board"
    )
    auto_reconnect: bool = param(True, "reopen the port by name after the board vanishes")
    reconnect_interval_s: float = param(0.25, "wait between attempts to reopen a vanished port")
    calibration_file: Path | None = param(
        None, "per-taxel zero and gain (TOML, see docs/tactile-wire.md); unset = uniform below"
    )
    zero_counts: float = param(0.0, "uniform zero offset in counts, when no calibration_file")
    gain_n_per_count: float = param(0.003, "uniform gain, newtons per count, when no file")
    floor_n: float = param(1.0, "the sensor's floor: a taxel below this reads 0 N")
    saturation_n: float = param(SATURATION_N, "the sensor's ceiling: a taxel above this reads this")
    mirror_finger2: bool = param(True, "finger 2 faces finger 1: reverse its columns")
    zero_on_connect_frames: int = param(
        0, "capture the zero from this many frames at connect (only if nothing is grasped then)"
    )

    def __post_init__(self) -> None:
        for name in ("max_age_ms", "connect_timeout_s", "read_timeout_s", "reconnect_interval_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, not {getattr(self, name)!r}")
        if not self.gain_n_per_count > 0:
            raise ValueError("gain_n_per_count must be positive")
        if not 0 <= self.floor_n < self.saturation_n:
            raise ValueError("need 0 <= floor_n < saturation_n")
        if self.zero_on_connect_frames < 0:
            raise ValueError("zero_on_connect_frames must not be negative")
        if self.baudrate <= 0:
            raise ValueError(f"baudrate must be positive, not {self.baudrate}")
