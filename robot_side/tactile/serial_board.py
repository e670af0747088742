"""The tactile board driver: pyserial, a background reader, per-taxel calibration.

The reader thread owns the port and the stream parser; it pairs the two pads
of a scan by sequence number, converts counts to newtons, mirrors finger 2
into the common view and publishes the frame. Callers only ever see the
newest frame (``read_latest``), and a frame older than the caller accepts is
an error that says why: the board went silent, sends only garbage (a wrong
baud rate), or vanished from the bus (unplugged; the reader reopens the port
by name until it comes back).

Wire format: robot_side/tactile/wire.py and docs/tactile-wire.md.
"""

from __future__ import annotations

import logging
import os
import select
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import serial

from common.clock import now_ns
from common.config import param
from common.devices import Device
from common.errors import (
    ConfigError,
    DeviceAlreadyConnectedError,
    DeviceError,
    DeviceTimeoutError,
    ProtocolError,
    StaleDataError,
)
from common.preflight import Finding, PreflightContext, serial_findings
from common.tactile import SATURATION_N
from robot_side.tactile.base import GraspTruth, TactileSample, TactileSensor
from robot_side.tactile.board_calibration import (
    WIRE_SHAPE,
    BoardCalibration,
    load_board_calibration,
    save_board_calibration,
)
from robot_side.tactile.wire import (
    DEFAULT_BAUD,
    SEQ_MODULO,
    PadPacket,
    StreamParser,
    counts_of,
)

log = logging.getLogger(__name__)

_PORT_HINT = "list the connected boards with `ls -l /dev/serial/by-id` and set `port`"
#: bytes taken per read: everything a line at 921600 baud delivers in 40 ms
_READ_SIZE = 4096


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


class SerialTactileSensor(TactileSensor):
    """The two pads on one serial line: newest frame first, errors that say why."""

    Config = SerialTactileConfig

    def __init__(self, config: SerialTactileConfig | None = None) -> None:
        super().__init__()
        self.config = config or SerialTactileConfig()
        cfg = self.config
        self._calibration: BoardCalibration = BoardCalibration.uniform(
            cfg.zero_counts, cfg.gain_n_per_count
        )
        self._explicit_calibration = False
        self._ser: serial.Serial | None = None
        self._ser_lock = threading.Lock()  # open/close races between reader and disconnect()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._running = False
        self._parser = StreamParser()
        self._link = "closed"  # closed | open | down
        self._link_error: str | None = None
        self._link_down_ns = 0
        self._last_byte_ns = 0
        self._last_packet_ns = 0
        # Pairing the two pads of one scan (their payloads, as sent).
        self._pending_seq: int | None = None
        self._pending: dict[int, bytes] = {}
        self._converter: ScanConverter | None = None
        self._last_wire_seq: int | None = None
        self._published_seq = 0
        self._raw_sinks: list[list[np.ndarray]] = []
        self._sink_cond = threading.Condition()
        self._counters = {
            "frames": 0,
            "incomplete_frames": 0,
            "seq_gaps": 0,
            "duplicate_frames": 0,
            "board_restarts": 0,
            "disconnects": 0,
            "reconnects": 0,
        }

    # -- calibration ------------------------------------------------------------

    @property
    def calibration(self) -> BoardCalibration:
        return self._calibration

    def set_calibration(self, calibration: BoardCalibration) -> None:
        """Use this calibration from the next frame on (and at connect, over the config)."""
        self._calibration = calibration
        self._explicit_calibration = True

    def capture_zero(self, n_frames: int = 60, timeout_s: float | None = None) -> np.ndarray:
        """Average ``n_frames`` raw frames as the new zero; NOTHING may touch the pads.

        Returns the zero ``FRAME_SHAPE`` frame in counts, wire view. Keeps the gains.
        """
        self.require_connected()
        if n_frames < 1:
            raise ValueError("n_frames must be at least 1")
        timeout_s = timeout_s if timeout_s is not None else 1.0 + 3 * n_frames / 120
        sink: list[np.ndarray] = []
        with self._sink_cond:
            self._raw_sinks.append(sink)
            try:
                ok = self._sink_cond.wait_for(lambda: len(sink) >= n_frames, timeout_s)
            finally:
                self._raw_sinks.remove(sink)
        if not ok:
            raise DeviceTimeoutError(
                f"capture_zero: got {len(sink)} of {n_frames} frames from {self.config.port} "
                f"in {timeout_s:.1f} s; is the board streaming? ({self._diagnosis()})"
            )
        stack = np.stack(sink[:n_frames]).astype(np.float64)
        zero = stack.mean(axis=0)
        spread = float(stack.std(axis=0).max())
        newtons_spread = float((stack.std(axis=0) * self._calibration.gain_n_per_count).max())
        if newtons_spread > 0.5 * self.config.floor_n:
            log.warning(
                "capture_zero: a taxel varied by %.0f counts (%.2f N) while zeroing; "
                "was something touching the pads?",
                spread,
                newtons_spread,
            )
        self._calibration = BoardCalibration(zero, self._calibration.gain_n_per_count)
        log.info("tactile zero captured from %d frames (max spread %.1f counts)", n_frames, spread)
        return zero

    def save_calibration(self, path: str | Path) -> None:
        save_board_calibration(self._calibration, path)

    # -- lifecycle --------------------------------------------------------------

    def _preflight(self, context: PreflightContext) -> list[Finding]:
        return serial_findings(self.config.port, self.config.baudrate, context)

    def _location(self) -> str:
        return f"on {self.config.port} at {self.config.baudrate} baud"

    @property
    def is_connected(self) -> bool:
        return self._running

    def connect(self) -> None:
        if self._running:
            raise DeviceAlreadyConnectedError(f"tactile board on {self.config.port} is connected")
        cfg = self.config
        if cfg.calibration_file is not None and not self._explicit_calibration:
            self._calibration = load_board_calibration(cfg.calibration_file)
        self._reset_stream_state()
        self._converter = ScanConverter(self._calibration, cfg)  # compiled before the first scan
        self._ser = self._open_port()  # missing port or no permission: raise now, by name
        self._link = "open"
        self._stop.clear()
        self._running = True
        self._thread = threading.Thread(
            target=self._reader, name=f"tactile-{os.path.basename(cfg.port)}", daemon=True
        )
        self._thread.start()
        try:
            if self.wait_for_frame(self._published_seq, cfg.connect_timeout_s) is None:
                raise self._no_frame_error(cfg.connect_timeout_s)
            if cfg.zero_on_connect_frames:
                self.capture_zero(cfg.zero_on_connect_frames)
        except BaseException:
            self.disconnect()
            raise
        log.info("tactile board streaming on %s at %d baud", cfg.port, cfg.baudrate)

    def disconnect(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            if self._thread.is_alive():
                log.warning("tactile reader thread did not stop within 2 s")
        self._thread = None
        self._close_port()
        self._running = False
        self._link = "closed"

    def reconnect(self) -> None:
        """Close and open again: for when auto_reconnect is off or a port was renamed."""
        self.disconnect()
        self.connect()

    # -- reading ----------------------------------------------------------------

    def read_latest(self, max_age_ms: float | None = None) -> TactileSample:
        """The newest frame; ``StaleDataError`` naming the cause when it is too old."""
        limit = self.config.max_age_ms if max_age_ms is None else max_age_ms
        try:
            return super().read_latest(limit)
        except StaleDataError as e:
            raise StaleDataError(f"{e} [{self._diagnosis()}]") from None

    def stats(self) -> dict[str, int]:
        s = self._parser.stats.as_dict()
        s.update(self._counters)
        return s

    def status(self) -> dict[str, Any]:
        s = Device.status(self)
        s.update(port=self.config.port, baudrate=self.config.baudrate, link=self._link)
        if self._link_error:
            s["link_error"] = self._link_error
        s.update(self.stats())
        return s

    # -- hooks for simulation ---------------------------------------------------

    def _truth_for_wire_seq(self, wire_seq: int) -> GraspTruth | None:
        """Ground truth of a frame: a real board has none; a simulated one overrides."""
        return None

    # -- internals --------------------------------------------------------------

    def _open_port(self) -> serial.Serial:
        cfg = self.config
        if not os.path.exists(cfg.port):
            raise DeviceError(f"tactile board port {cfg.port} does not exist: {_PORT_HINT}")
        try:
            return serial.Serial(
                cfg.port, baudrate=cfg.baudrate, timeout=cfg.read_timeout_s, exclusive=True
            )
        except ValueError as e:  # pyserial rejects the rate or a setting
            raise ConfigError(
                f"tactile board: baudrate {cfg.baudrate} rejected by {cfg.port}: {e}"
            ) from e
        except serial.SerialException as e:
            if isinstance(e.__context__, PermissionError) or "Permission denied" in str(e):
                raise DeviceError(
                    f"no permission to open {cfg.port}: add yourself to the dialout group "
                    "(`sudo usermod -aG dialout $USER`, then log in again)"
                ) from e
            if "lock" in str(e).lower():
                raise DeviceError(
                    f"{cfg.port} is already open in another process (only one reader allowed)"
                ) from e
            raise DeviceError(
                f"cannot open tactile board port {cfg.port}: {e}; {_PORT_HINT}"
            ) from e

    def _close_port(self) -> None:
        with self._ser_lock:
            ser, self._ser = self._ser, None
        if ser is not None:
            try:
                ser.close()
            except (OSError, serial.SerialException) as e:
                log.debug("closing %s: %s", self.config.port, e)

    def _reset_stream_state(self) -> None:
        self._parser.reset()
        self._pending_seq = None
        self._pending = {}

    def _reader(self) -> None:
        cfg = self.config
        while not self._stop.is_set():
            ser = self._ser
            if ser is None:
                if not cfg.auto_reconnect:
                    self._stop.wait(cfg.read_timeout_s)
                    continue
                try:
                    opened = self._open_port()
                except (DeviceError, ConfigError) as e:
                    self._link_error = str(e)
                    self._stop.wait(cfg.reconnect_interval_s)
                    continue
                with self._ser_lock:
                    if self._stop.is_set():
                        opened.close()
                        break
                    self._ser = opened
                self._reset_stream_state()
                self._link = "open"
                self._link_error = None
                self._counters["reconnects"] += 1
                log.warning("tactile board on %s is back; reading again", cfg.port)
                continue
            # pyserial opened and configured the port; reading goes straight to its
            # fd: one select and one read per wake-up. pyserial's read(in_waiting
            # or 1) took a byte, then an ioctl, a second select and read for the
            # rest: about 100 us more per scan on a cold core.
            try:
                fd = ser.fileno()
                if not select.select((fd,), (), (), cfg.read_timeout_s)[0]:
                    continue
                chunk = os.read(fd, _READ_SIZE)
                if not chunk:  # readable yet empty: the device is gone (pyserial says the same)
                    raise serial.SerialException(
                        "device reports readiness to read but returned no data "
                        "(device disconnected or multiple access on port?)"
                    )
            except BlockingIOError:  # the fd is non-blocking; another reader took the bytes
                continue
            except (OSError, ValueError, serial.SerialException, TypeError, AttributeError) as e:
                # ValueError/TypeError/AttributeError: the port closed from another thread.
                if self._stop.is_set():
                    break
                self._on_link_lost(e)
                continue
            t = now_ns()
            self._last_byte_ns = t
            for packet in self._parser.feed(chunk):
                self._last_packet_ns = t
                self.accept_packet(packet, t)

    def _on_link_lost(self, error: BaseException) -> None:
        self._counters["disconnects"] += 1
        self._link = "down"
        self._link_down_ns = now_ns()
        self._link_error = f"{type(error).__name__}: {error}"
        self._close_port()
        log.error(
            "tactile board on %s vanished (%s); %s",
            self.config.port,
            error,
            "reopening it when it comes back" if self.config.auto_reconnect else "not reconnecting",
        )

    def feed(self, data: bytes, t_ns: int) -> None:
        """Bytes from the board, arrived at ``t_ns``, as the reader thread takes them.

        The bench and replays drive the driver this way, without a port or a thread.
        """
        for packet in self.parse(data):
            self.accept_packet(packet, t_ns)

    def parse(self, data: bytes) -> list[PadPacket]:
        """``feed``'s first half: the packets the bytes complete (the bench times it alone)."""
        return self._parser.feed(data)

    def accept_packet(self, packet: PadPacket, t_ns: int) -> None:
        """``feed``'s second half: pair the pads of a scan; a complete scan becomes a frame."""
        if packet.seq != self._pending_seq:
            if self._pending:
                self._counters["incomplete_frames"] += 1
            self._pending = {}
            self._pending_seq = packet.seq
        pending = self._pending
        pending[packet.pad] = packet.payload
        if len(pending) == WIRE_SHAPE[0]:
            self._pending = {}
            self._pending_seq = None
            self._on_scan(packet.seq, pending[0] + pending[1], t_ns)

    def _on_scan(self, wire_seq: int, payloads: bytes, t_ns: int) -> None:
        """Both pads' count bytes, pad 0 first: published raw, in newtons when read."""
        seq = self._next_seq(wire_seq)
        if seq is None:
            return
        if self._raw_sinks:
            counts = counts_of(payloads).reshape(WIRE_SHAPE)
            with self._sink_cond:
                for sink in self._raw_sinks:
                    sink.append(counts)
                self._sink_cond.notify_all()
        converter = self._converter
        if converter is None or converter.calibration is not self._calibration:
            converter = self._converter = ScanConverter(self._calibration, self.config)
        self._counters["frames"] += 1
        self._publish_raw(seq, t_ns, payloads, converter, self._truth_for_wire_seq(wire_seq))

    def _next_seq(self, wire_seq: int) -> int | None:
        """Map the board's wrapping uint32 onto a count that only grows.

        The first frame ever seen gets the board's number + 1 (so a scan's
        wire number is ``seq - 1`` until the board restarts, which keeps logs
        comparable with the board's). A forward jump keeps its size (gaps
        stay visible as drops); a step back means the board restarted (power
        cycle, replug), which must not make the published sequence go back.
        """
        last = self._last_wire_seq
        self._last_wire_seq = wire_seq
        if last is None:
            self._published_seq = wire_seq + 1
            return self._published_seq
        else:
            d = (wire_seq - last) % SEQ_MODULO
            if d == 0:
                self._counters["duplicate_frames"] += 1
                return None
            if d < SEQ_MODULO // 2:
                step = d
                self._counters["seq_gaps"] += d - 1
            else:
                step = 1
                self._counters["board_restarts"] += 1
                log.warning(
                    "tactile board sequence went back (%d -> %d): restarted?", last, wire_seq
                )
        self._published_seq += step
        return self._published_seq

    def _diagnosis(self) -> str:
        """One line on why frames are missing, for error messages."""
        cfg = self.config
        now = now_ns()
        if not self._running:
            return "not connected"
        if self._link == "down":
            down_ms = (now - self._link_down_ns) / 1e6
            again = "reopening it" if cfg.auto_reconnect else "auto_reconnect is off: reconnect()"
            return (
                f"board on {cfg.port} vanished {down_ms:.0f} ms ago ({self._link_error}); {again}"
            )
        st = self._parser.stats
        if self._last_byte_ns == 0:
            return (
                f"nothing received on {cfg.port} since it was opened: board powered and streaming?"
            )
        silent_ms = (now - self._last_byte_ns) / 1e6
        if silent_ms > 2 * 1000 / 120:
            return (
                f"board on {cfg.port} has sent nothing for {silent_ms:.0f} ms: it stopped streaming"
            )
        since_packet_ms = (now - self._last_packet_ns) / 1e6 if self._last_packet_ns else None
        if since_packet_ms is None or since_packet_ms > 50:
            return (
                f"bytes arrive on {cfg.port} but no valid packet "
                f"(bad_crc={st.bad_crc}, bad_header={st.bad_header}, dropped_bytes="
                f"{st.dropped_bytes}): wrong baud rate? baudrate = {cfg.baudrate}, "
                "it must match the firmware"
            )
        return (
            f"packets arrive but frames are incomplete "
            f"(incomplete_frames={self._counters['incomplete_frames']})"
        )

    def _no_frame_error(self, waited_s: float) -> DeviceError:
        cfg = self.config
        st = self._parser.stats
        if self._link == "down":
            return DeviceError(
                f"tactile board on {cfg.port} vanished while connecting: {self._link_error}"
            )
        if st.bytes_in == 0:
            return DeviceTimeoutError(
                f"opened {cfg.port} at {cfg.baudrate} baud but the tactile board sent nothing in "
                f"{waited_s:.1f} s: is it powered and streaming? Is this the right port? "
                f"({_PORT_HINT})"
            )
        if st.packets == 0:
            return ProtocolError(
                f"received {st.bytes_in} bytes on {cfg.port} in {waited_s:.1f} s but not one valid "
                f"packet (bad_crc={st.bad_crc}, bad_header={st.bad_header}): wrong baud rate? "
                f"baudrate = {cfg.baudrate} must match the board firmware (docs/tactile-wire.md); "
                "or this is not a tactile board"
            )
        return ProtocolError(
            f"{st.packets} packets from {cfg.port} in {waited_s:.1f} s but no complete frame "
            "(both pads with one sequence number); "
            f"incomplete={self._counters['incomplete_frames']}"
        )


class ScanConverter:
    """Count bytes of one scan -> a ``FRAME_SHAPE`` float32 frame in newtons, common view.

    newtons = (counts - zero) * gain per taxel, above saturation clipped,
    below the floor 0; finger 2's columns reversed. The calibration arrays
    are put in the common view once, so the mirror is one gather of counts.
    Float32 throughout: counts are exact in it, and the rounding (about
    1e-5 N) is far below the ADC's step; one dtype means one conversion less
    per frame. With numba installed the conversion is one compiled call
    (``compiled.convert_scan``, bit-identical); ``numpy_path`` is the reference.
    """

    def __init__(self, calibration: BoardCalibration, config: SerialTactileConfig) -> None:
        self.calibration = calibration
        index = np.arange(np.prod(WIRE_SHAPE)).reshape(WIRE_SHAPE)
        if config.mirror_finger2:
            index[1] = index[1, :, ::-1]
        self._index = index.reshape(-1).astype(np.intp)
        self._order = None if not config.mirror_finger2 else self._index
        self._zero = calibration.zero_counts.reshape(-1)[self._index].astype(np.float32)
        self._gain = calibration.gain_n_per_count.reshape(-1)[self._index].astype(np.float32)
        self._floor = np.float32(config.floor_n)
        self._saturation = np.float32(config.saturation_n)
        self._compiled = _compiled_converter()
        if self._compiled is not None:  # compile (or load the cache) now, not on a frame
            self(bytes(2 * self._index.size))

    def __call__(self, payloads: bytes) -> np.ndarray:
        if self._compiled is not None:
            if len(payloads) != 2 * self._index.size:  # compiled code does not bounds-check
                raise ValueError(
                    f"a scan is {2 * self._index.size} count bytes, not {len(payloads)}"
                )
            return self._compiled(
                payloads, self._index, self._zero, self._gain, self._floor, self._saturation
            )
        return self.numpy_path(payloads)

    def numpy_path(self, payloads: bytes) -> np.ndarray:
        counts = counts_of(payloads)
        if self._order is not None:
            counts = counts.take(self._order)
        newtons = (counts - self._zero) * self._gain
        np.minimum(newtons, self._saturation, out=newtons)
        newtons[newtons < self._floor] = 0.0
        return newtons.reshape(WIRE_SHAPE)


def _compiled_converter() -> Any:
    try:
        from robot_side.tactile.compiled import convert_scan
    except ImportError:  # numba is in the robot extra; NumPy does the same, slower
        return None
    except Exception as e:  # a broken numba install must not stop the sensor
        log.warning("compiled tactile conversion unavailable (%s); using NumPy", e)
        return None
    return convert_scan
