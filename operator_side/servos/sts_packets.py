"""The fake STS bus's wire: instruction packets parsed and answered as the servos would.

PING, READ, WRITE, REG_WRITE, ACTION, SYNC_READ and SYNC_WRITE; a packet whose
checksum fails is dropped (as a servo does, silently); a silent servo hears
nothing; replies may be dropped or corrupted on request. Every goal that
reaches a servo, and every torque off, is logged.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable

from common.clocks.clock import now_ns
from operator_side.servos.sts_registers import (
    BROADCAST_ID,
    GOAL_POSITION,
    INST_ACTION,
    INST_READ,
    INST_REG_WRITE,
    INST_SYNC_READ,
    INST_SYNC_WRITE,
    INST_WRITE,
    INSTRUCTIONS,
    checksum,
    packet,
)
from operator_side.servos.sts_servo import FakeServo


class StsResponder:
    """Bytes from the driver in (``feed``), the servos' status packets out (``send``).

    ``advance`` brings every servo's position up to now before an
    instruction is applied; the bus's ``counters``, ``goal_log`` and
    ``release_log`` are written here. ``drop`` and ``corrupt`` hold the
    pending reply faults: the servo id each targets, or None for any.
    """

    def __init__(
        self,
        servos: dict[int, FakeServo],
        counters: dict[str, int],
        goal_log: deque[tuple[int, int, int]],
        release_log: deque[tuple[int, int, int]],
        send: Callable[[bytes], None],
        advance: Callable[[], None],
    ) -> None:
        self._servos = servos
        self.counters = counters
        self.goal_log = goal_log
        self.release_log = release_log
        self._send = send
        self._advance = advance
        self.drop: list[int | None] = []
        self.corrupt: list[int | None] = []
        self._buf = bytearray()

    def feed(self, data: bytes) -> None:
        """Bytes off the line: every whole packet in them handled."""
        self._buf += data
        self._parse()

    def clear(self) -> None:
        """The line went away (unplugged): a half-received packet is gone with it."""
        self._buf.clear()

    def _parse(self) -> None:
        buf = self._buf
        while True:
            i = buf.find(b"\xff\xff")
            if i < 0:
                del buf[: max(0, len(buf) - 1)]  # a lone trailing 0xFF may start a header
                return
            # Skip extra 0xFF before the id (FF FF FF id ... is still a header).
            while i + 2 < len(buf) and buf[i + 2] == 0xFF:
                i += 1
            del buf[:i]
            if len(buf) < 4:
                return
            length = buf[3]
            if length < 2:
                self.counters["bad_length"] += 1
                del buf[:2]
                continue
            total = length + 4
            if len(buf) < total:
                return
            pkt = bytes(buf[:total])
            if checksum(pkt[2:-1]) != pkt[-1]:
                self.counters["bad_checksum"] += 1
                del buf[:2]  # a servo ignores it; look for the next header
                continue
            del buf[:total]
            self.counters["packets"] += 1
            self._handle(pkt[2], pkt[4], pkt[5:-1])

    def _handle(self, sid: int, inst: int, params: bytes) -> None:
        self._advance()
        name = INSTRUCTIONS.get(inst)
        if name is None:
            self.counters["unknown_instruction"] += 1
            return
        self.counters[name.lower()] += 1
        if inst == INST_SYNC_WRITE:
            if len(params) < 2:
                return
            address, size = params[0], params[1]
            body = params[2:]
            for k in range(0, len(body) - size, size + 1):
                target = self._servos.get(body[k])
                if target is not None and not target.silent:
                    self._write(target, address, body[k + 1 : k + 1 + size])
            return
        if inst == INST_SYNC_READ:
            if len(params) < 2:
                return
            address, size = params[0], params[1]
            for target_id in params[2:]:
                target = self._servos.get(target_id)
                if target is not None and not target.silent:
                    self._reply(target, bytes(target.table[address : address + size]))
            return
        targets = (
            list(self._servos.values())
            if sid == BROADCAST_ID
            else [self._servos[sid]]
            if sid in self._servos
            else []
        )
        for servo in targets:
            if servo.silent:
                continue
            data = b""
            if inst == INST_READ:
                if len(params) != 2:
                    continue
                address, size = params
                data = bytes(servo.table[address : address + size])
            elif inst == INST_WRITE and params:
                self._write(servo, params[0], params[1:])
            elif inst == INST_REG_WRITE and params:
                servo.pending = (params[0], bytes(params[1:]))
            elif inst == INST_ACTION and servo.pending is not None:
                self._write(servo, *servo.pending)
                servo.pending = None
            if sid != BROADCAST_ID:
                self._reply(servo, data)

    def _write(self, servo: FakeServo, address: int, data: bytes) -> None:
        was_on = servo.torque
        servo.write(address, data)
        goal = GOAL_POSITION.address
        if address <= goal < address + len(data) and address <= goal + 1 < address + len(data):
            self.goal_log.append((now_ns(), servo.id, servo.goal))
        if was_on and not servo.torque:
            self.release_log.append((now_ns(), servo.id, round(servo.position)))

    def _reply(self, servo: FakeServo, data: bytes) -> None:
        if self._take(self.drop, servo.id):
            self.counters["dropped_replies"] += 1
            return
        reply = bytearray(packet(servo.id, servo.error_bits, data))
        if self._take(self.corrupt, servo.id):
            reply[-1] ^= 0x5A
            self.counters["corrupted_replies"] += 1
        self.counters["replies"] += 1
        self._send(bytes(reply))

    @staticmethod
    def _take(faults: list[int | None], sid: int) -> bool:
        for k, target in enumerate(faults):
            if target is None or target == sid:
                del faults[k]
                return True
        return False
