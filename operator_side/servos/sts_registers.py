"""The Feetech STS control table and instruction set, as data.

One table shared by the driver and the fake bus, so an address is written
once. Values are for the STS series (STS3215 and kin) in protocol_end 0:
multi-byte registers are little-endian. 4096 counts per turn.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


@dataclass(frozen=True, slots=True)
class Register:
    name: str
    address: int
    size: int  # bytes
    access: Literal["r", "rw"]
    eeprom: bool  # persists across power cycles; writable only with lock = 0


REGISTERS: tuple[Register, ...] = (
    # EEPROM
    Register("firmware_major", 0, 1, "r", True),
    Register("firmware_minor", 1, 1, "r", True),
    Register("model_number", 3, 2, "r", True),
    Register("id", 5, 1, "rw", True),
    Register("baud_rate", 6, 1, "rw", True),
    Register("return_delay", 7, 1, "rw", True),
    Register("status_return_level", 8, 1, "rw", True),
    Register("min_angle_limit", 9, 2, "rw", True),
    Register("max_angle_limit", 11, 2, "rw", True),
    Register("max_temperature", 13, 1, "rw", True),
    Register("max_voltage", 14, 1, "rw", True),
    Register("min_voltage", 15, 1, "rw", True),
    Register("max_torque", 16, 2, "rw", True),
    Register("phase", 18, 1, "rw", True),
    Register("unloading_condition", 19, 1, "rw", True),
    Register("led_alarm_condition", 20, 1, "rw", True),
    Register("p_coefficient", 21, 1, "rw", True),
    Register("d_coefficient", 22, 1, "rw", True),
    Register("i_coefficient", 23, 1, "rw", True),
    Register("minimum_startup_force", 24, 2, "rw", True),
    Register("cw_dead_zone", 26, 1, "rw", True),
    Register("ccw_dead_zone", 27, 1, "rw", True),
    Register("protection_current", 28, 2, "rw", True),
    Register("angular_resolution", 30, 1, "rw", True),
    Register("homing_offset", 31, 2, "rw", True),
    Register("operating_mode", 33, 1, "rw", True),
    Register("protective_torque", 34, 1, "rw", True),
    Register("protection_time", 35, 1, "rw", True),
    Register("overload_torque", 36, 1, "rw", True),
    # SRAM
    Register("torque_enable", 40, 1, "rw", False),
    Register("acceleration", 41, 1, "rw", False),
    Register("goal_position", 42, 2, "rw", False),
    Register("goal_time", 44, 2, "rw", False),
    Register("goal_speed", 46, 2, "rw", False),
    Register("torque_limit", 48, 2, "rw", False),
    Register("lock", 55, 1, "rw", False),
    Register("present_position", 56, 2, "r", False),
    Register("present_speed", 58, 2, "r", False),
    Register("present_load", 60, 2, "r", False),
    Register("present_voltage", 62, 1, "r", False),
    Register("present_temperature", 63, 1, "r", False),
    Register("status", 65, 1, "r", False),
    Register("moving", 66, 1, "r", False),
    Register("present_current", 69, 2, "r", False),
)

REG: dict[str, Register] = {r.name: r for r in REGISTERS}

#: bytes of the control table a servo (or the fake bus) holds
TABLE_SIZE = 128

# Addresses used often enough to deserve a name.
MODEL_NUMBER = REG["model_number"]
TORQUE_ENABLE = REG["torque_enable"]
ACCELERATION = REG["acceleration"]
GOAL_POSITION = REG["goal_position"]
GOAL_SPEED = REG["goal_speed"]
LOCK = REG["lock"]
PRESENT_POSITION = REG["present_position"]
PRESENT_SPEED = REG["present_speed"]
MOVING = REG["moving"]

#: model numbers known to this project (the value at address 3); others are named by number
MODEL_NUMBERS: dict[int, str] = {777: "STS3215"}

# Instructions.
INST_PING = 0x01
INST_READ = 0x02
INST_WRITE = 0x03
INST_REG_WRITE = 0x04
INST_ACTION = 0x05
INST_SYNC_READ = 0x82
INST_SYNC_WRITE = 0x83
INSTRUCTIONS: dict[int, str] = {
    INST_PING: "PING",
    INST_READ: "READ",
    INST_WRITE: "WRITE",
    INST_REG_WRITE: "REG_WRITE",
    INST_ACTION: "ACTION",
    INST_SYNC_READ: "SYNC_READ",
    INST_SYNC_WRITE: "SYNC_WRITE",
}
BROADCAST_ID = 0xFE
MAX_ID = 0xFC

# Error bits of a status packet.
ERR_VOLTAGE = 0x01
ERR_ANGLE = 0x02
ERR_OVERHEAT = 0x04
ERR_OVERCURRENT = 0x08
ERR_OVERLOAD = 0x20
ERROR_BITS: dict[int, str] = {
    ERR_VOLTAGE: "input voltage",
    ERR_ANGLE: "angle sensor",
    ERR_OVERHEAT: "overheat",
    ERR_OVERCURRENT: "overcurrent",
    ERR_OVERLOAD: "overload",
}

#: value of the baud_rate register -> bits per second
BAUD_RATES: dict[int, int] = {
    0: 1_000_000,
    1: 500_000,
    2: 250_000,
    3: 128_000,
    4: 115_200,
    5: 57_600,
    6: 38_400,
    7: 19_200,
}

COUNTS_PER_TURN = 4096


def describe_error(bits: int) -> str:
    """'overload, overheat' for a status packet's error byte; '' when clear."""
    return ", ".join(name for bit, name in ERROR_BITS.items() if bits & bit)


def checksum(body: bytes | bytearray) -> int:
    """~(ID + LEN + INST/ERR + params) & 0xFF, over the bytes after FF FF."""
    return ~sum(body) & 0xFF


def packet(sid: int, inst_or_err: int, params: bytes | bytearray = b"") -> bytes:
    """A complete instruction or status packet: FF FF ID LEN X P... CHK."""
    body = bytes([sid, len(params) + 2, inst_or_err]) + bytes(params)
    return b"\xff\xff" + body + bytes([checksum(body)])
