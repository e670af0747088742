"""Robotiq 2F over Modbus RTU on its own serial line (USB/RS-485 adapter), via pyserial.

The register map (Robotiq 2F manual, "Control logic"): three 16-bit
registers each way, two bytes per register, high byte first.

Robot -> gripper, written with function 16 from 0x03E8::

    byte 0  action request: rACT bit 0, rGTO bit 3, rATR bit 4, rARD bit 5
    byte 1  reserved        byte 2  reserved
    byte 3  rPR position    byte 4  rSP speed     byte 5  rFR force

Gripper -> robot, read with function 4 from 0x07D0::

    byte 0  status: gACT bit 0, gGTO bit 3, gSTA bits 4-5, gOBJ bits 6-7
    byte 1  reserved
    byte 2  faults: gFLT low nibble, kFLT high nibble
    byte 3  gPR echo        byte 4  gPO position  byte 5  gCU current (x 10 mA)

Frames end with CRC-16/Modbus, low byte first. The gripper's slave id is 9.
"""

from __future__ import annotations

import logging
import struct
import threading
from dataclasses import dataclass

from common.config.typed import param
from common.devices.preflight import Finding, PreflightContext, serial_findings
from common.errors import (
    DeviceAlreadyConnectedError,
    DeviceNotConnectedError,
    DeviceTimeoutError,
    ProtocolError,
)
from robot_side.gripper.base import GripLevels, Gripper, GripperState

log = logging.getLogger(__name__)

SLAVE_ID = 9
BAUDRATE = 115200
OUTPUT_REGISTERS = 0x03E8  # robot -> gripper (the manual's "robot output")
INPUT_REGISTERS = 0x07D0  # gripper -> robot
N_REGISTERS = 3
FC_READ_INPUT_REGISTERS = 0x04
FC_READ_HOLDING_REGISTERS = 0x03
FC_WRITE_MULTIPLE_REGISTERS = 0x10

ACT_BIT = 0x01
GTO_BIT = 0x08
ATR_BIT = 0x10

MODBUS_EXCEPTIONS = {
    1: "illegal function",
    2: "illegal data address",
    3: "illegal data value",
    4: "slave device failure",
}


def crc16(data: bytes) -> int:
    """CRC-16/Modbus: reflected polynomial 0xA001, initial value 0xFFFF."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


def with_crc(frame: bytes) -> bytes:
    return frame + struct.pack("<H", crc16(frame))


def crc_ok(frame: bytes) -> bool:
    return len(frame) >= 4 and crc16(frame[:-2]) == struct.unpack("<H", frame[-2:])[0]


def write_request(slave: int, address: int, data: bytes) -> bytes:
    """Function 16: write ``len(data) // 2`` registers from ``address``."""
    head = struct.pack(
        ">BBHHB", slave, FC_WRITE_MULTIPLE_REGISTERS, address, len(data) // 2, len(data)
    )
    return with_crc(head + data)


def read_request(
    slave: int, address: int, count: int, function: int = FC_READ_INPUT_REGISTERS
) -> bytes:
    return with_crc(struct.pack(">BBHH", slave, function, address, count))


def command_bytes(
    act: bool, go: bool, position: int, speed: int, force: int, atr: bool = False
) -> bytes:
    """The six robot-side register bytes (see the module docstring)."""
    action = (ACT_BIT if act else 0) | (GTO_BIT if go else 0) | (ATR_BIT if atr else 0)
    return bytes([action, 0, 0, position, speed, force])


def parse_status(data: bytes) -> GripperState:
    status, _, faults, pr, po, _current = data
    return GripperState(
        activation=(status >> 4) & 0x03,
        goto=bool(status & GTO_BIT),
        object_status=(status >> 6) & 0x03,
        fault=faults & 0x0F,
        requested_position=pr,
        position=po,
    )


@dataclass
class RobotiqRtuConfig:
    port: str = param("/dev/ttyUSB0", "serial device of the USB/RS-485 adapter")
    baudrate: int = param(BAUDRATE, "the 2F's fixed rate")
    slave_id: int = param(SLAVE_ID, "Robotiq grippers answer as slave 9")
    reply_timeout_s: float = param(0.1, "a reply is ~1 ms on the wire; allow for USB latency")
    retries: int = param(1, "re-sends after a timeout or bad CRC before giving up")
    activation_timeout_s: float = param(5.0, "activation takes about 1.5 s on a 2F-85")
    activate_on_connect: bool = param(
        True, "activate at connect if not active (an inactive gripper refuses every move)"
    )
    levels: GripLevels = param(GripLevels(), "grip level 1..31 -> position and force")


class RobotiqRtuGripper(Gripper):
    Config = RobotiqRtuConfig

    def __init__(self, config: RobotiqRtuConfig | None = None) -> None:
        self.config = config or RobotiqRtuConfig()
        super().__init__(self.config.levels, self.config.activation_timeout_s)
        self._serial = None
        self._io_lock = threading.Lock()
        self._act = False  # rACT as last written: every write carries it
        self.crc_errors = 0
        self.timeouts = 0
        self.transactions = 0

    def _preflight(self, context: PreflightContext) -> list[Finding]:
        return serial_findings(self.config.port, self.config.baudrate, context)

    def _location(self) -> str:
        return f"on {self.config.port} at {self.config.baudrate} baud"

    @property
    def is_connected(self) -> bool:
        return self._serial is not None

    def connect(self) -> None:
        if self._serial is not None:
            raise DeviceAlreadyConnectedError(f"gripper on {self.config.port} is already connected")
        import serial

        try:
            self._serial = serial.Serial(
                self.config.port,
                self.config.baudrate,
                bytesize=8,
                parity="N",
                stopbits=1,
                timeout=self.config.reply_timeout_s,
            )
        except (serial.SerialException, ValueError) as e:
            raise DeviceNotConnectedError(
                f"gripper: cannot open {self.config.port} at {self.config.baudrate} baud ({e}); "
                "check the adapter is plugged in and you are in the 'dialout' group"
            ) from e
        try:
            st = self._read_state()  # proves a gripper answers before we claim to be connected
            self._act = st.activation != 0
            log.info("gripper on %s answers (STA=%d)", self.config.port, st.activation)
            if self.config.activate_on_connect:
                self.activate()
        except Exception:
            self.disconnect()
            raise

    def disconnect(self) -> None:
        ser, self._serial = self._serial, None
        if ser is not None:
            ser.close()
            log.info("gripper on %s closed", self.config.port)

    # -- wire ----------------------------------------------------------------

    def _transact(self, request: bytes, reply_len: int) -> bytes:
        """Send one frame, read one reply; retries on timeout or bad CRC."""
        with self._io_lock:
            ser = self._serial
            if ser is None:
                raise DeviceNotConnectedError(
                    f"gripper on {self.config.port} is not connected: call connect() first"
                )
            last = ""
            for _attempt in range(self.config.retries + 1):
                ser.reset_input_buffer()
                ser.write(request)
                ser.flush()
                head = ser.read(2)
                if len(head) < 2:
                    self.timeouts += 1
                    last = "no reply"
                    continue
                if head[0] != self.config.slave_id:
                    self.crc_errors += 1
                    last = f"reply from slave {head[0]}, expected {self.config.slave_id}"
                    continue
                if head[1] & 0x80:  # exception: code byte and CRC follow
                    rest = ser.read(3)
                    frame = head + rest
                    if len(frame) == 5 and crc_ok(frame):
                        code = frame[2]
                        raise ProtocolError(
                            f"gripper on {self.config.port} refused function {head[1] & 0x7F}: "
                            f"Modbus exception {code} ({MODBUS_EXCEPTIONS.get(code, 'unknown')})"
                        )
                    self.crc_errors += 1
                    last = "corrupt exception reply"
                    continue
                rest = ser.read(reply_len - 2)
                frame = head + rest
                if len(frame) < reply_len:
                    self.timeouts += 1
                    last = f"reply cut short ({len(frame)} of {reply_len} bytes)"
                    continue
                if not crc_ok(frame) or frame[1] != request[1]:
                    self.crc_errors += 1
                    last = "bad CRC" if not crc_ok(frame) else "reply to another function"
                    continue
                self.transactions += 1
                return frame
            if last.startswith("no reply") or last.startswith("reply cut"):
                raise DeviceTimeoutError(
                    f"gripper on {self.config.port} (slave {self.config.slave_id}): {last} after "
                    f"{self.config.retries + 1} tries; check power, wiring, the baud rate "
                    f"({self.config.baudrate}) and that nothing else holds the port"
                )
            raise ProtocolError(
                f"gripper on {self.config.port}: {last} after {self.config.retries + 1} tries; "
                "check for noise on the RS-485 line and a second master"
            )

    def _write(self, data: bytes) -> None:
        req = write_request(self.config.slave_id, OUTPUT_REGISTERS, data)
        frame = self._transact(req, 8)
        address, count = struct.unpack(">HH", frame[2:6])
        if address != OUTPUT_REGISTERS or count != len(data) // 2:
            raise ProtocolError(
                f"gripper on {self.config.port} acknowledged a write of {count} registers at "
                f"0x{address:04X}, not {len(data) // 2} at 0x{OUTPUT_REGISTERS:04X}"
            )

    # -- Gripper hooks -------------------------------------------------------

    def _write_activate(self) -> None:
        self._write(command_bytes(False, False, 0, 0, 0))
        self._write(command_bytes(True, False, 0, 0, 0))
        self._act = True

    def _write_command(self, position: int, speed: int, force: int, go: bool) -> None:
        self._write(command_bytes(self._act, go, position, speed, force))

    def _read_state(self) -> GripperState:
        req = read_request(self.config.slave_id, INPUT_REGISTERS, N_REGISTERS)
        frame = self._transact(req, 5 + 2 * N_REGISTERS)
        if frame[2] != 2 * N_REGISTERS:
            raise ProtocolError(
                f"gripper on {self.config.port} returned {frame[2]} data bytes, "
                f"not {2 * N_REGISTERS}"
            )
        return parse_status(frame[3 : 3 + 2 * N_REGISTERS])

    def status(self) -> dict[str, object]:
        out = super().status()
        out.update(
            port=self.config.port,
            transactions=self.transactions,
            crc_errors=self.crc_errors,
            timeouts=self.timeouts,
        )
        return out
