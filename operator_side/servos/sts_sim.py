"""A fake Feetech STS bus on a pseudo-terminal: real packets, real checksums.

The real driver and the unchanged feetech-servo-sdk talk to it through
pyserial exactly as to a USB bus adapter. It decodes instruction packets
(PING, READ, WRITE, REG_WRITE, ACTION, SYNC_READ, SYNC_WRITE), drops those
whose checksum fails (as a servo does, silently), keeps a control table per
servo (model number at address 3, so the SDK's ping works), moves each
present position towards its goal at a finite speed while torque is on, and
answers with status packets. On request it drops or corrupts replies, lets a
servo fall silent, raises error bits, lets a hand move a limp linkage, and
unplugs. It also logs every goal position that reached a servo, so a test
can prove that an out-of-limit count never got onto the wire.

Byte order is STS (protocol_end 0, little-endian) only.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import select
import threading
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Self

from common.clock import now_ns
from common.config import param
from common.devices import OnItsSimulator, as_hardware
from common.errors import ConfigError
from common.pty_link import PtyLink
from operator_side.servos.feetech import FeetechConfig, FeetechServoBus
from operator_side.servos.sts_registers import (
    BAUD_RATES,
    BROADCAST_ID,
    GOAL_POSITION,
    INST_ACTION,
    INST_READ,
    INST_REG_WRITE,
    INST_SYNC_READ,
    INST_SYNC_WRITE,
    INST_WRITE,
    INSTRUCTIONS,
    MODEL_NUMBER,
    MOVING,
    PRESENT_POSITION,
    PRESENT_SPEED,
    REG,
    TABLE_SIZE,
    TORQUE_ENABLE,
    checksum,
    packet,
)

log = logging.getLogger(__name__)

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


class _Servo:
    def __init__(self, sid: int, cfg: FakeStsBusConfig) -> None:
        self.id = sid
        self.table = bytearray(TABLE_SIZE)
        self.silent = False
        self.error_bits = 0
        self.pending: tuple[int, bytes] | None = None  # REG_WRITE waiting for ACTION
        self.position = float(cfg.start_counts)
        self._put(MODEL_NUMBER.address, 2, cfg.model_number)
        self._put(REG["id"].address, 1, sid)
        baud_code = next(k for k, v in BAUD_RATES.items() if v == cfg.baudrate)
        self._put(REG["baud_rate"].address, 1, baud_code)
        self._put(REG["max_angle_limit"].address, 2, 4095)
        self._put(REG["max_torque"].address, 2, 1000)
        self._put(REG["torque_limit"].address, 2, 1000)
        self._put(GOAL_POSITION.address, 2, cfg.start_counts)
        self._put(PRESENT_POSITION.address, 2, cfg.start_counts)
        self._put(REG["present_voltage"].address, 1, cfg.voltage_decivolts)
        self._put(REG["present_temperature"].address, 1, cfg.temperature_c)

    def _put(self, address: int, size: int, value: int) -> None:
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
            self._put(MOVING.address, 1, 0)
            self._put(PRESENT_SPEED.address, 2, 0)

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
        self._put(PRESENT_POSITION.address, 2, round(self.position) & 0xFFFF)
        # STS speed: magnitude with bit 15 as the sign.
        self._put(PRESENT_SPEED.address, 2, velocity | (0x8000 if delta < 0 and velocity else 0))
        self._put(MOVING.address, 1, moving)


class FakeStsBus:
    """Servos on a pty. ``port`` is the name to open; start/stop or ``with``."""

    def __init__(self, config: FakeStsBusConfig | None = None) -> None:
        self.config = cfg = config or FakeStsBusConfig()
        self._servos = {sid: _Servo(sid, cfg) for sid in cfg.ids}
        self._link = PtyLink("sts-bus", cfg.link_dir)
        self._lock = threading.RLock()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._buf = bytearray()
        self._last_ns = now_ns()
        self._drop: list[int | None] = []  # per pending fault: the servo id it targets, or any
        self._corrupt: list[int | None] = []
        self._stalled_until_ns = 0
        self.goal_log: deque[tuple[int, int, int]] = deque(maxlen=cfg.goal_log_size)
        #: (t_ns, id, present position) of each torque off: where a servo was let go (a
        #: linkage let go mid-way stays there, maybe on the palm)
        self.release_log: deque[tuple[int, int, int]] = deque(maxlen=cfg.goal_log_size)
        self.counters: dict[str, int] = {
            "packets": 0,
            "bad_checksum": 0,
            "bad_length": 0,
            "replies": 0,
            "dropped_replies": 0,
            "corrupted_replies": 0,
            "stalls": 0,
            "unknown_instruction": 0,
            "wrong_baud_bytes": 0,
        }
        for name in INSTRUCTIONS.values():
            self.counters[name.lower()] = 0

    # -- lifecycle ----------------------------------------------------------------

    @property
    def port(self) -> str:
        return str(self._link.path)

    @property
    def slave_path(self) -> str | None:
        return self._link.slave_path

    def start(self) -> Self:
        if self._thread is not None:
            raise RuntimeError("fake STS bus already started")
        with self._lock:
            self._link.plug()
        self._stop.clear()
        self._thread = threading.Thread(
            target=as_hardware(self._run), name="fake-sts-bus", daemon=True
        )
        self._thread.start()
        log.info("fake STS bus (ids %s) on %s -> %s", self.config.ids, self.port, self.slave_path)
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._thread = None
        with self._lock:
            self._link.close()

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- faults and the physical world ----------------------------------------------

    def drop_replies(self, n: int = 1, sid: int | None = None) -> None:
        """The next ``n`` replies (from ``sid``, or any servo) never arrive."""
        with self._lock:
            self._drop.extend([sid] * n)

    def stall(self, seconds: float) -> None:
        """Hear nothing for ``seconds``, then answer everything sent meanwhile at once: the
        simulator's process held up by its machine (or an adapter's USB latency spike)."""
        with self._lock:
            self._stalled_until_ns = now_ns() + round(seconds * 1e9)
            self.counters["stalls"] += 1

    def corrupt_replies(self, n: int = 1, sid: int | None = None) -> None:
        """The next ``n`` replies arrive with a wrong checksum (line noise)."""
        with self._lock:
            self._corrupt.extend([sid] * n)

    def set_silent(self, sid: int, silent: bool = True) -> None:
        """A servo that hears and says nothing: unpowered, or its cable is off."""
        with self._lock:
            self._servos[sid].silent = silent

    def set_error_bits(self, sid: int, bits: int) -> None:
        """Error byte of this servo's status packets (ERR_OVERLOAD, ...)."""
        with self._lock:
            self._servos[sid].error_bits = bits

    def move_by_hand(self, sid: int, counts: int) -> None:
        """Someone moves a limp linkage; a servo holding torque resists and stays."""
        with self._lock:
            servo = self._servos[sid]
            if not servo.torque:
                servo.position = float(counts)
                servo._put(PRESENT_POSITION.address, 2, counts & 0xFFFF)

    def unplug(self) -> None:
        """Unplug the adapter: the pty and its name disappear."""
        with self._lock:
            self._link.unplug()
            self._buf.clear()

    def replug(self) -> None:
        """Plug it back: a new pty behind the same name; servos keep their state."""
        with self._lock:
            if not self._link.plugged_in:
                self._link.plug()

    # -- inspection -----------------------------------------------------------------

    def present(self, sid: int) -> int:
        with self._lock:
            self._advance()
            return self._servos[sid].get(PRESENT_POSITION.address, 2)

    def goal(self, sid: int) -> int:
        with self._lock:
            return self._servos[sid].goal

    def torque(self, sid: int) -> bool:
        with self._lock:
            return self._servos[sid].torque

    def register(self, sid: int, name: str) -> int:
        reg = REG[name]
        with self._lock:
            self._advance()
            return self._servos[sid].get(reg.address, reg.size)

    def stats(self) -> dict[str, int]:
        with self._lock:
            return dict(self.counters)

    # -- the wire -------------------------------------------------------------------

    def _run(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                master = self._link.master
                stalled_s = (self._stalled_until_ns - now_ns()) / 1e9
            if stalled_s > 0:  # bytes wait in the pty meanwhile
                self._stop.wait(stalled_s)
                continue
            if master is None:
                self._stop.wait(0.01)
                continue
            try:
                ready, _, _ = select.select([master], [], [], 0.02)
            except (OSError, ValueError):
                continue  # unplugged under our feet
            if not ready:
                continue
            with self._lock:
                if self._link.master != master:
                    continue
                try:
                    data = os.read(master, 4096)
                except (BlockingIOError, OSError):
                    continue
                if not self._link.line_speed_is(self.config.baudrate):
                    # At the wrong rate a UART sees framing errors: nothing to answer.
                    if not self.counters["wrong_baud_bytes"]:
                        log.warning(
                            "fake STS bus on %s: the driver's line is not at %d baud; "
                            "the servos hear noise and answer nothing",
                            self.port,
                            self.config.baudrate,
                        )
                    self.counters["wrong_baud_bytes"] += len(data)
                    continue
                self._buf += data
                self._parse()

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

    def _write(self, servo: _Servo, address: int, data: bytes) -> None:
        was_on = servo.torque
        servo.write(address, data)
        goal = GOAL_POSITION.address
        if address <= goal < address + len(data) and address <= goal + 1 < address + len(data):
            self.goal_log.append((now_ns(), servo.id, servo.goal))
        if was_on and not servo.torque:
            self.release_log.append((now_ns(), servo.id, round(servo.position)))

    def _reply(self, servo: _Servo, data: bytes) -> None:
        if self._take(self._drop, servo.id):
            self.counters["dropped_replies"] += 1
            return
        reply = bytearray(packet(servo.id, servo.error_bits, data))
        if self._take(self._corrupt, servo.id):
            reply[-1] ^= 0x5A
            self.counters["corrupted_replies"] += 1
        self.counters["replies"] += 1
        self._link.write(bytes(reply))

    @staticmethod
    def _take(faults: list[int | None], sid: int) -> bool:
        for k, target in enumerate(faults):
            if target is None or target == sid:
                del faults[k]
                return True
        return False

    def _advance(self) -> None:
        now = now_ns()
        dt = (now - self._last_ns) / 1e9
        self._last_ns = now
        for servo in self._servos.values():
            servo.advance(dt, self.config.speed_counts_per_s)


# -- the scene kind: the real driver on the fake bus ------------------------------------


@dataclass
class SimulatedFeetechConfig:
    bus: FakeStsBusConfig = param(FakeStsBusConfig(), "the fake servos (speed, faults, ...)")
    # A wider reply window and more retries than a real bus needs: the fake servos answer
    # from a thread of this process, which a loaded machine can hold up past 34 ms.
    driver: FeetechConfig = param(
        FeetechConfig(retries=3, reply_timeout_ms=150.0),
        "the real driver's settings; its port is set to the fake bus",
    )


#: what the simulated bus's driver changes from the real driver's defaults
SIMULATED_DRIVER_KEYS = ("retries", "reply_timeout_ms")


def simulated_driver_settings(config: SimulatedFeetechConfig | None = None) -> dict[str, Any]:
    """The driver settings a node (or ``deepxpalm palm lift``) needs on the simulated bus run
    as a process of its own (``deepxpalm sim servos``): the wider reply window and retries.

    Its replies ride a pseudo-terminal, whose bytes the kernel's workers carry at ordinary
    priority: beside a loaded machine's other work a round trip took up to 290 ms, so the
    real bus's 34 ms window with two retries let a ping go unanswered.
    """
    driver = (config or SimulatedFeetechConfig()).driver
    return {k: getattr(driver, k) for k in SIMULATED_DRIVER_KEYS}


class SimulatedFeetechServoBus(OnItsSimulator, FeetechServoBus):
    """The real ``FeetechServoBus`` (and the real SDK) on a fake STS bus."""

    Config = SimulatedFeetechConfig  # type: ignore[assignment]

    def __init__(self, config: SimulatedFeetechConfig | None = None) -> None:
        self.sim_config = config or SimulatedFeetechConfig()
        super().__init__(self.sim_config.driver)
        self.fake_bus = FakeStsBus(self.sim_config.bus)

    def _start_simulator(self) -> None:
        self.fake_bus.start()
        self.config = dataclasses.replace(self.config, port=self.fake_bus.port)

    def _stop_simulator(self) -> None:
        self.fake_bus.stop()

    def status(self) -> dict[str, Any]:
        s = super().status()
        s["fake_bus"] = self.fake_bus.stats()
        return s
