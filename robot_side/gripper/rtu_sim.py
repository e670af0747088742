"""A Robotiq 2F answering Modbus RTU on a pseudo-terminal, for the RTU driver.

The simulator holds the pty's master end and answers slave 9's function 16
writes at 0x03E8 and function 4 (and 3) reads at 0x07D0 with real frames
and CRCs, driving the same ``GripperModel`` as the socket simulator. It also
keeps the slave end open, so the driver opening ``port`` is not the only
holder (a pty whose last slave holder closes reports EIO to the master).

Frames are cut by function code rather than by the 3.5-character silence
of real RTU (a pty has no timing); a bad CRC drops one byte and tries again,
so garbage is skipped, and a partial frame followed by ``SILENCE_S`` of
quiet is dropped byte by byte. Fault injection: ``drop_next`` replies, ``corrupt_next``
replies, ``mute``.
"""

from __future__ import annotations

import contextlib
import logging
import os
import select
import struct
import threading
import tty

from common.devices.lifecycle import as_hardware
from robot_side.gripper.modbus_rtu import (
    FC_READ_HOLDING_REGISTERS,
    FC_READ_INPUT_REGISTERS,
    FC_WRITE_MULTIPLE_REGISTERS,
    INPUT_REGISTERS,
    OUTPUT_REGISTERS,
    SLAVE_ID,
    crc_ok,
    with_crc,
)
from robot_side.gripper.model import GripperModel, GripperModelConfig

log = logging.getLogger(__name__)

#: Silence that ends a frame. RTU says 3.5 characters (0.3 ms at 115200 baud);
#: a pty shared with a busy test machine needs more slack.
SILENCE_S = 0.01


class RtuGripperSim:
    """``start()`` then open ``port`` with the RTU driver."""

    def __init__(self, model: GripperModelConfig | None = None, slave_id: int = SLAVE_ID) -> None:
        self.model = GripperModel(model)
        self.slave_id = slave_id
        self.port = ""
        self._master = self._slave = -1
        self._quit = threading.Event()
        self._threads: list[threading.Thread] = []
        self._written = bytes(6)  # last robot-side registers
        self.drop_next = 0
        self.corrupt_next = 0
        self.muted = False
        self.frames = 0
        self.crc_errors = 0

    def start(self) -> RtuGripperSim:
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo, no line discipline: bytes as sent
        self.port = os.ttyname(self._slave)
        self._quit.clear()
        for name, target in (("tick", self._tick_loop), ("serve", self._serve_loop)):
            t = threading.Thread(target=as_hardware(target), name=f"rtusim-{name}", daemon=True)
            self._threads.append(t)
            t.start()
        log.info("RTU gripper simulator on %s", self.port)
        return self

    def stop(self) -> None:
        self._quit.set()
        for t in self._threads:
            t.join(timeout=2.0)
        self._threads.clear()
        for fd in (self._master, self._slave):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._master = self._slave = -1

    def __enter__(self) -> RtuGripperSim:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _tick_loop(self) -> None:
        self.model.run(self._quit)

    def _serve_loop(self) -> None:
        buf = b""
        while not self._quit.is_set():
            # a pending partial frame followed by silence is noise (real RTU cuts frames
            # on 3.5 characters of silence): drop a byte and look again
            ready, _, _ = select.select([self._master], [], [], SILENCE_S if buf else 0.05)
            if not ready:
                if buf:
                    self.crc_errors += 1
                    buf = self._consume(buf[1:])
                continue
            try:
                buf += os.read(self._master, 4096)
            except OSError:
                return
            buf = self._consume(buf)

    def _consume(self, buf: bytes) -> bytes:
        while len(buf) >= 8:
            fc = buf[1]
            # a write's length is in its byte count; reads (and unknown functions) are 8 bytes
            n = 9 + buf[6] if fc == FC_WRITE_MULTIPLE_REGISTERS else 8
            if len(buf) < n:
                return buf  # wait for the rest
            frame = buf[:n]
            if not crc_ok(frame):
                self.crc_errors += 1
                buf = buf[1:]  # resynchronise one byte later
                continue
            buf = buf[n:]
            self.frames += 1
            if frame[0] != self.slave_id:
                continue  # another slave's frame: stay silent
            reply = self._answer(frame)
            if reply is not None:
                self._send(reply)
        return buf

    def _send(self, reply: bytes) -> None:
        if self.muted:
            return
        if self.drop_next > 0:
            self.drop_next -= 1
            return
        if self.corrupt_next > 0:
            self.corrupt_next -= 1
            reply = reply[:-1] + bytes([reply[-1] ^ 0xFF])
        os.write(self._master, reply)

    def _answer(self, frame: bytes) -> bytes | None:
        sid, fc = frame[0], frame[1]
        if fc == FC_WRITE_MULTIPLE_REGISTERS:
            address, count, nbytes = struct.unpack(">HHB", frame[2:7])
            data = frame[7 : 7 + nbytes]
            if address != OUTPUT_REGISTERS or count != 3 or nbytes != 6:
                return _exception(sid, fc, 2)
            self._apply(data)
            return with_crc(frame[:6])
        if fc in (FC_READ_INPUT_REGISTERS, FC_READ_HOLDING_REGISTERS):
            address, count = struct.unpack(">HH", frame[2:6])
            if address == INPUT_REGISTERS and 1 <= count <= 3:
                data = self._status_bytes()[: 2 * count]
            elif address == OUTPUT_REGISTERS and 1 <= count <= 3:
                data = self._written[: 2 * count]
            else:
                return _exception(sid, fc, 2)
            return with_crc(bytes([sid, fc, len(data)]) + data)
        return _exception(sid, fc, 1)

    def _apply(self, data: bytes) -> None:
        self._written = bytes(data)
        action = data[0]
        self.model.write(
            ACT=action & 0x01,
            ATR=(action >> 4) & 0x01,
            POS=data[3],
            SPE=data[4],
            FOR=data[5],
            GTO=(action >> 3) & 0x01,
        )

    def _status_bytes(self) -> bytes:
        r = self.model.read()
        status = r["ACT"] | (r["GTO"] << 3) | (r["STA"] << 4) | (r["OBJ"] << 6)
        return bytes([status, 0, r["FLT"] & 0x0F, r["PRE"], r["POS"], min(255, r["CUR"])])


def _exception(slave: int, function: int, code: int) -> bytes:
    return with_crc(bytes([slave, function | 0x80, code]))
