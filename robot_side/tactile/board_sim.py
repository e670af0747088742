"""A tactile board on a pseudo-terminal: the real wire, scripted grasps behind it.

The simulator is what a developer compares a real board with, byte for byte:
it encodes with the same ``wire`` module, at 120 Hz on absolute deadlines,
turns newtons into ADC counts through its own per-taxel zero and gain (so the
driver's calibration has real work to do), and sends finger 2 in its own
view, un-mirrored, as the hardware does. It can misbehave on request:
garbage, bad CRCs, dropped bytes, lost scans, silence, and an unplug.

``port`` is a symlink to the current pty slave, like a /dev/serial/by-id
name: after ``unplug()`` and ``replug()`` the pty is new but the name
is the same, so the driver's reopen-by-name is exercised as on a USB replug.

What the pads feel comes from the grasp script, or from a ``ContactSource``
(a physics world's taxel forces and ground truth); either way it goes
through the same pad model (gain spread, noise, floor, saturation, dead and
stuck taxels) and the same ADC calibration before it reaches the wire.

The simulator also remembers the ground truth of each scan it sent
(``truth_for(seq)``), so a node in the same process can score what it
inferred; ``SimulatedSerialTactileSensor`` (kind ``simulated_serial``) attaches
it to each sample, and the node code does not change.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import threading
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, Self

import numpy as np

from common.clocks.clock import Rate, now_ns
from common.config.typed import param
from common.devices.lifecycle import OnItsSimulator, as_hardware
from common.devices.pty_link import PtyLink
from common.tactile.synthetic import GeneratorParams, HeldGrasp, SyntheticTactileModel
from robot_side.tactile.base import GraspTruth
from robot_side.tactile.board_calibration import WIRE_SHAPE, BoardCalibration
from robot_side.tactile.script import GraspScript
from robot_side.tactile.serial_board import SerialTactileConfig, SerialTactileSensor
from robot_side.tactile.wire import DEFAULT_BAUD, PACKET_SIZE, SEQ_MODULO, encode

log = logging.getLogger(__name__)


class ContactSource(Protocol):
    """Where the pads' true contact forces come from when a world feeds the board."""

    def contact_at(self, t_s: float) -> tuple[np.ndarray, GraspTruth]:
        """``FRAME_SHAPE`` true normal force per taxel (N, common view) and what is grasped."""


@dataclass
class TactileBoardSimConfig:
    rate_hz: float = param(120.0, "scans per second, as the real board")
    seed: int = param(0, "seeds the pad model, the ADC calibration and the grasp variation")
    script: GraspScript = param(GraspScript(), "the grasps the pads feel")
    generator: GeneratorParams = param(GeneratorParams(), "the synthetic pad model (newtons)")
    baudrate: int = param(
        DEFAULT_BAUD, "the firmware's rate: a driver opening another sees garbage"
    )
    zero_counts_min: float = param(150.0, "ADC zero offsets are drawn per taxel in [min, max]")
    zero_counts_max: float = param(450.0, "ADC zero offsets are drawn per taxel in [min, max]")
    counts_at_9n: float = param(3000.0, "nominal counts above zero at 9 N (12-bit ADC headroom)")
    gain_spread: float = param(0.05, "std dev of per-taxel ADC gain (log-normal)")
    count_noise: float = param(1.0, "std dev of ADC noise, counts (well under the 1 N floor)")
    first_seq: int = param(0, "sequence number of the first scan (uint32, wraps)")
    history: int = param(1024, "scans whose truth and frame are kept for truth_for/frame_for")
    link_dir: Path | None = param(None, "where the stable port symlink lives; unset = temp dir")

    def __post_init__(self) -> None:
        if not self.rate_hz > 0:
            raise ValueError("rate_hz must be positive")
        if not 0 <= self.zero_counts_min <= self.zero_counts_max:
            raise ValueError("need 0 <= zero_counts_min <= zero_counts_max")
        if not self.counts_at_9n > 0 or self.history < 1:
            raise ValueError("counts_at_9n and history must be positive")


class TactileBoardSimulator:
    """The simulated board: start/stop (or ``with``), fault injection, ground truth."""

    def __init__(
        self, config: TactileBoardSimConfig | None = None, source: ContactSource | None = None
    ) -> None:
        self.config = cfg = config or TactileBoardSimConfig()
        #: a world's contact forces; None: the grasp script and the synthetic band model
        self.source = source
        self._model = SyntheticTactileModel(cfg.generator, seed=cfg.seed)
        crng = np.random.default_rng([cfg.seed, 0x7AC])
        zero = crng.uniform(cfg.zero_counts_min, cfg.zero_counts_max, WIRE_SHAPE)
        gain = 9.0 / cfg.counts_at_9n * np.exp(crng.normal(0.0, cfg.gain_spread, WIRE_SHAPE))
        #: the exact inverse of how this board makes counts: its "factory calibration"
        self.calibration = BoardCalibration(zero, gain)
        self._rng = np.random.default_rng([cfg.seed, 0x5CE])
        self._held = HeldGrasp(self._model, self._rng)
        self._fault_rng = np.random.default_rng([cfg.seed, 0xBAD])
        self._lock = threading.Lock()
        self._pty: PtyLink | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._paused = threading.Event()
        self._seq = cfg.first_seq % SEQ_MODULO
        self._history: OrderedDict[int, tuple[GraspTruth, np.ndarray]] = OrderedDict()
        self._streaming = threading.Event()  # set by the first scan after start()
        # Faults waiting to be applied to the next packets.
        self._garbage = bytearray()
        self._corrupt = 0
        self._drop: list[int] = []
        self._skip = 0
        self.counters = {
            "scans": 0,
            "bytes_written": 0,
            "overflow_bytes": 0,
            "wrong_baud_scans": 0,
            "corrupted_packets": 0,
            "truncated_packets": 0,
            "skipped_scans": 0,
            "garbage_bytes": 0,
            "rate_overruns": 0,
        }

    # -- lifecycle ----------------------------------------------------------------

    @property
    def port(self) -> str:
        """The stable name to open (a symlink to the current pty slave)."""
        if self._pty is None:
            raise RuntimeError("tactile board simulator is not started")
        return str(self._pty.path)

    @property
    def slave_path(self) -> str | None:
        """The current pty slave itself (changes on every reconnect)."""
        return None if self._pty is None else self._pty.slave_path

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    @property
    def plugged_in(self) -> bool:
        return self._pty is not None and self._pty.plugged_in

    def start(self) -> Self:
        if self._thread is not None:
            raise RuntimeError("tactile board simulator already started")
        self._pty = PtyLink("tactile-board", self.config.link_dir)
        self._pty.plug()
        self._stop.clear()
        self._streaming.clear()
        self._thread = threading.Thread(
            target=as_hardware(self._run), name="tactile-board-sim", daemon=True
        )
        self._thread.start()
        log.info("tactile board simulator on %s -> %s", self._pty.path, self._pty.slave_path)
        return self

    def wait_streaming(self, timeout_s: float = 10.0) -> None:
        """Until the first scan is out: a powered board streams before anyone opens its port.

        So a driver's ``connect_timeout_s`` (a real board's first frame) never counts the
        simulator's own start, which a busy machine can stretch past it.
        """
        if not self._streaming.wait(timeout_s):
            raise TimeoutError(f"the tactile board simulator sent no scan in {timeout_s:.0f} s")

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._thread = None
        if self._pty is not None:
            self._pty.close()

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- faults -------------------------------------------------------------------

    def inject_garbage(self, n_bytes: int, with_sync: bool = True) -> None:
        """Random bytes before the next packet; ``with_sync`` sprinkles false sync pairs."""
        junk = bytearray(self._fault_rng.integers(0, 256, n_bytes, dtype=np.uint8).tobytes())
        if with_sync and n_bytes >= 4:
            for k in range(0, n_bytes - 1, 37):
                junk[k : k + 2] = b"\xa5\x5a"
        with self._lock:
            self._garbage += junk

    def corrupt_next(self, n_packets: int = 1) -> None:
        """Flip one payload bit in each of the next packets: their CRC fails."""
        with self._lock:
            self._corrupt += n_packets

    def drop_bytes_next(self, n_bytes: int = 17, n_packets: int = 1) -> None:
        """Cut ``n_bytes`` out of the middle of the next packets (a UART overrun)."""
        if not 0 < n_bytes < PACKET_SIZE:
            raise ValueError(f"n_bytes must be in 1..{PACKET_SIZE - 1}")
        with self._lock:
            self._drop.extend([n_bytes] * n_packets)

    def skip_scans(self, n_scans: int) -> None:
        """Lose whole scans on the board (sequence numbers still advance)."""
        with self._lock:
            self._skip += n_scans

    def pause(self) -> None:
        """Stop streaming but stay plugged in: a hung firmware."""
        self._paused.set()

    def resume(self) -> None:
        self._paused.clear()

    def unplug(self) -> None:
        """Pull the USB cable: close the pty and remove the port name. Streaming stops."""
        with self._lock:
            if self._pty is not None:
                self._pty.unplug()
        log.info("tactile board simulator unplugged")

    def replug(self) -> None:
        """Plug back in: a new pty behind the same port name. Sequence numbers continue."""
        with self._lock:
            if self._pty is not None and not self._pty.plugged_in:
                self._pty.plug()
        log.info("tactile board simulator plugged in again -> %s", self.slave_path)

    # -- ground truth ---------------------------------------------------------------

    def truth_for(self, seq: int) -> GraspTruth | None:
        """What scan ``seq`` (the wire sequence number) showed; None once forgotten."""
        with self._lock:
            entry = self._history.get(seq % SEQ_MODULO)
        return None if entry is None else entry[0]

    def frame_for(self, seq: int) -> np.ndarray | None:
        """The newtons (common view, before ADC quantisation) sent as scan ``seq``."""
        with self._lock:
            entry = self._history.get(seq % SEQ_MODULO)
        return None if entry is None else entry[1]

    def scan_at(self, t_s: float) -> None:
        """One scan at script time ``t_s``, as the scan thread makes it.

        Unplugged, nobody hears it, but its newtons and truth are kept
        (``frame_for``, ``truth_for``): the bench replays a script this way.
        """
        self._scan(t_s)

    def stats(self) -> dict[str, int]:
        return dict(self.counters)

    # -- internals ------------------------------------------------------------------

    def _run(self) -> None:
        cfg = self.config
        rate = Rate(cfg.rate_hz)
        t0 = now_ns()
        while not self._stop.is_set():
            if not self._paused.is_set():
                self._scan((now_ns() - t0) / 1e9)
            remaining = rate.remaining_s()
            if remaining > 0:
                self._stop.wait(remaining)
            rate.advance()
            self.counters["rate_overruns"] = rate.overruns

    def _scan(self, t_s: float) -> None:
        cfg = self.config
        if self.source is not None:
            force, truth = self.source.contact_at(t_s)
            frame = self._model.sense(force, self._rng)
        else:
            truth = cfg.script.truth_at(t_s)
            frame = self._held.frame(truth.pattern, truth.grip_level)
        wire_newtons = frame.astype(np.float64)
        wire_newtons[1] = wire_newtons[1, :, ::-1].copy()  # finger 2 in its own view
        counts = self.calibration.to_counts(wire_newtons)
        if cfg.count_noise > 0:
            counts += self._rng.normal(0.0, cfg.count_noise, WIRE_SHAPE)
        counts = np.clip(np.rint(counts), 0, 0xFFFF).astype(np.uint16)
        with self._lock:
            seq = self._seq
            self._seq = (seq + 1) % SEQ_MODULO
            self._history[seq] = (truth, frame)
            while len(self._history) > cfg.history:
                self._history.popitem(last=False)
            if self._skip > 0:
                self._skip -= 1
                self.counters["skipped_scans"] += 1
                return
            data = bytearray(self._garbage)
            self.counters["garbage_bytes"] += len(self._garbage)
            self._garbage.clear()
            for pad in range(WIRE_SHAPE[0]):
                data += self._faulty(encode(pad, seq, counts[pad]))
            self.counters["scans"] += 1
            self._streaming.set()
            master = None if self._pty is None else self._pty.master
            if master is None:
                return  # unplugged: the scan happens, nobody hears it
            if not self._pty.line_speed_is(cfg.baudrate):
                self.counters["wrong_baud_scans"] += 1
                data = bytearray(
                    self._fault_rng.integers(0, 256, len(data), dtype=np.uint8).tobytes()
                )
            # Written with the lock held: an unplug cannot close the fd (and the
            # number be reused by another open) between the check and the write.
            self._write(master, bytes(data))

    def _faulty(self, packet: bytes) -> bytes:
        """Apply the next pending fault to one packet (called with the lock held)."""
        if self._corrupt > 0:
            self._corrupt -= 1
            self.counters["corrupted_packets"] += 1
            b = bytearray(packet)
            b[PACKET_SIZE // 2] ^= 0x10
            return bytes(b)
        if self._drop:
            n = self._drop.pop(0)
            self.counters["truncated_packets"] += 1
            cut = PACKET_SIZE // 2
            return packet[:cut] + packet[cut + n :]
        return packet

    def _write(self, master: int, data: bytes) -> None:
        try:
            written = os.write(master, data)
        except BlockingIOError:
            written = 0
        except OSError as e:  # unplugged between the lock and the write
            log.debug("tactile board simulator write failed: %s", e)
            return
        self.counters["bytes_written"] += written
        if written < len(data):
            # Nobody is reading fast enough: a real UART's bytes are simply lost.
            self.counters["overflow_bytes"] += len(data) - written


# -- the scene kind: the real driver against this simulator ---------------------------


@dataclass
class SimulatedSerialConfig:
    board: TactileBoardSimConfig = param(
        TactileBoardSimConfig(), "the simulated board (script, pad model, ADC, baud)"
    )
    driver: SerialTactileConfig = param(
        SerialTactileConfig(), "the real driver's settings; its port is set to the simulator's"
    )
    use_factory_calibration: bool = param(
        True, "give the driver the board's exact zero and gain, unless driver.calibration_file"
    )


class SimulatedSerialTactileSensor(OnItsSimulator, SerialTactileSensor):
    """The real ``SerialTactileSensor`` reading a simulated board on a pty.

    Only the port and the calibration come from the simulator; every byte
    goes through pyserial and the real parser. Samples carry the board's
    ground truth, looked up by wire sequence number.
    """

    Config = SimulatedSerialConfig  # type: ignore[assignment]

    def __init__(self, config: SimulatedSerialConfig | None = None) -> None:
        self.sim_config = config or SimulatedSerialConfig()
        super().__init__(self.sim_config.driver)
        self.simulator = TactileBoardSimulator(self.sim_config.board)

    def _start_simulator(self) -> None:
        self.simulator.start()
        self.simulator.wait_streaming()
        self.config = dataclasses.replace(self.config, port=self.simulator.port)
        if self.sim_config.use_factory_calibration and self.config.calibration_file is None:
            self.set_calibration(self.simulator.calibration)

    def _stop_simulator(self) -> None:
        self.simulator.stop()

    def _truth_for_wire_seq(self, wire_seq: int) -> GraspTruth | None:
        return self.simulator.truth_for(wire_seq)

    def status(self) -> dict[str, Any]:
        s = super().status()
        s["simulator"] = self.simulator.stats()
        return s
