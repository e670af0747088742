"""The Feetech servo bus's settings: the port, the ids, the calibration, how to retry."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from common.config.typed import param
from operator_side.servos.calibration import LinkGlideCalibration

#: the rates PortHandler.setBaudRate accepts; any other returns False
SDK_BAUD_RATES = (4800, 9600, 14400, 19200, 38400, 57600, 115200, 128000, 250000, 500000, 1000000)


@dataclass
class FeetechConfig:
    port: str = param("/dev/ttyUSB0", "the bus adapter; prefer its /dev/serial/by-id/... name")
    baudrate: int = param(1_000_000, "STS servos ship at 1 Mbaud; must be one the SDK accepts")
    ids: tuple[int, ...] = param((1, 2, 3, 4, 5, 6), "linkage n uses ids 2n+1 and 2n+2")
    # param() is this project's dataclasses.field; it copies mutable defaults.
    calibration: LinkGlideCalibration = param(
        LinkGlideCalibration(), "zero, direction and limits, used when calibration_file is unset"
    )
    calibration_file: Path | None = param(
        None, "TOML written by `deepxpalm calibrate`; overrides the inline calibration"
    )
    retries: int = param(2, "extra attempts after a corrupt or missing reply (one window each)")
    reply_timeout_ms: float | None = param(
        None,
        "how long to wait for a status packet; unset = the SDK's 34 ms. Raise it for an "
        "adapter whose USB latency timer is above 16 ms",
    )
    connect_timeout_s: float = param(
        2.0,
        "at connect, servos that did not answer (a ping, the first reads) are asked again "
        "until this long has passed (an STS servo answers about half a second after its "
        "supply comes on); 0 = once",
    )
    protocol_end: int = param(0, "0 = STS (little-endian), 1 = SCS; one per process (SDK global)")
    expected_model: int | None = param(
        None, "refuse servos with another model number (777 = STS3215); unset = any"
    )
    torque_on_connect: bool = param(
        True, "hold the present pose (clipped to the limits) with torque on after connect"
    )
    goal_speed: int | None = param(
        None, "servo speed limit written at connect, counts/s (0 = max); unset = leave it"
    )
    acceleration: int | None = param(
        None, "servo acceleration written at connect (x100 counts/s^2); unset = leave it"
    )

    def __post_init__(self) -> None:
        if self.baudrate not in SDK_BAUD_RATES:
            raise ValueError(
                f"baudrate {self.baudrate} is not one feetech-servo-sdk accepts: {SDK_BAUD_RATES}"
            )
        if not self.ids or len(set(self.ids)) != len(self.ids):
            raise ValueError(f"ids must be a non-empty list without repeats, not {self.ids}")
        if any(not 0 <= i <= 0xFC for i in self.ids):
            raise ValueError(f"servo ids must be in 0..252, not {self.ids}")
        if self.retries < 0:
            raise ValueError("retries must not be negative")
        if not 0.0 <= self.connect_timeout_s <= 60.0:
            raise ValueError(f"connect_timeout_s = {self.connect_timeout_s} is not in 0..60")
        if self.reply_timeout_ms is not None and not 1.0 <= self.reply_timeout_ms <= 1000.0:
            raise ValueError(f"reply_timeout_ms = {self.reply_timeout_ms} is not in 1..1000")
        if self.protocol_end not in (0, 1):
            raise ValueError("protocol_end must be 0 (STS) or 1 (SCS)")
        for name in ("goal_speed", "acceleration"):
            v = getattr(self, name)
            if v is not None and not 0 <= v <= (0xFF if name == "acceleration" else 0xFFFF):
                raise ValueError(f"{name} = {v} is out of the register's range")
