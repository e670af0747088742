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

The servos' model is ``sts_servo``'s, the packets ``sts_packets``'.
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
from typing import Any, Self

from common.clocks.clock import now_ns
from common.config.typed import param
from common.devices.lifecycle import OnItsSimulator, as_hardware
from common.devices.pty_link import PtyLink
from operator_side.servos.feetech import FeetechConfig, FeetechServoBus
from operator_side.servos.sts_packets import StsResponder
from operator_side.servos.sts_registers import INSTRUCTIONS, PRESENT_POSITION, REG
from operator_side.servos.sts_servo import FakeServo, FakeStsBusConfig

__all__ = [
    "FakeStsBus",
    "FakeStsBusConfig",
    "SimulatedFeetechConfig",
    "SimulatedFeetechServoBus",
    "simulated_driver_settings",
]

log = logging.getLogger(__name__)


class FakeStsBus:
    """Servos on a pty. ``port`` is the name to open; start/stop or ``with``."""

    def __init__(self, config: FakeStsBusConfig | None = None) -> None:
        self.config = cfg = config or FakeStsBusConfig()
        self._servos = {sid: FakeServo(sid, cfg) for sid in cfg.ids}
        self._link = PtyLink("sts-bus", cfg.link_dir)
        self._lock = threading.RLock()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._last_ns = now_ns()
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
        #: the instruction packets off the line, answered as the servos would
        self._packets = StsResponder(
            self._servos,
            self.counters,
            self.goal_log,
            self.release_log,
            self._link.write,
            self._advance,
        )

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
            self._packets.drop.extend([sid] * n)

    def stall(self, seconds: float) -> None:
        """Hear nothing for ``seconds``, then answer everything sent meanwhile at once: the
        simulator's process held up by its machine (or an adapter's USB latency spike)."""
        with self._lock:
            self._stalled_until_ns = now_ns() + round(seconds * 1e9)
            self.counters["stalls"] += 1

    def corrupt_replies(self, n: int = 1, sid: int | None = None) -> None:
        """The next ``n`` replies arrive with a wrong checksum (line noise)."""
        with self._lock:
            self._packets.corrupt.extend([sid] * n)

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
                servo.put(PRESENT_POSITION.address, 2, counts & 0xFFFF)

    def unplug(self) -> None:
        """Unplug the adapter: the pty and its name disappear."""
        with self._lock:
            self._link.unplug()
            self._packets.clear()

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
                self._packets.feed(data)

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
