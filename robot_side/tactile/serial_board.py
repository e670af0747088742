"""The tactile board driver: pyserial, a background reader, per-taxel calibration.

The reader thread owns the port and the stream parser; it pairs the two pads
of a scan by sequence number, converts counts to newtons, mirrors finger 2
into the common view and publishes the frame. Callers only ever see the
newest frame (``read_latest``), and a frame older than the caller accepts is
an error that says why: the board went silent, sends only garbage (a wrong
baud rate), or vanished from the bus (unplugged; the reader reopens the port
by name until it comes back).

Its parts: the port and the reader thread (``board_reader``), the pads of a
scan paired and numbered (``scans``) and the conversion to newtons
(``scan_converter``). Wire format: robot_side/tactile/wire.py and
docs/tactile-wire.md.
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path
from typing import Any

import numpy as np

from common.devices.lifecycle import Device
from common.devices.preflight import Finding, PreflightContext, serial_findings
from common.errors import DeviceAlreadyConnectedError, DeviceTimeoutError, StaleDataError
from robot_side.tactile.base import GraspTruth, TactileSample, TactileSensor
from robot_side.tactile.board_calibration import (
    WIRE_SHAPE,
    BoardCalibration,
    load_board_calibration,
    save_board_calibration,
)
from robot_side.tactile.board_reader import BoardReader
from robot_side.tactile.scan_converter import ScanConverter
from robot_side.tactile.scans import ScanPairing
from robot_side.tactile.serial_config import SerialTactileConfig
from robot_side.tactile.wire import PadPacket, StreamParser, counts_of

__all__ = ["ScanConverter", "SerialTactileConfig", "SerialTactileSensor"]

log = logging.getLogger(__name__)


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
        self._running = False
        self._parser = StreamParser()
        self._converter: ScanConverter | None = None
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
        #: the pads of each scan paired and numbered, then ``_on_scan``
        self._scans = ScanPairing(self._counters, self._on_scan)
        #: the port and the thread that reads it into the parser and the pairing
        self._reader = BoardReader(self._parser, self._scans, self._counters)

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
            why = self._reader.diagnosis(self._running)
            raise DeviceTimeoutError(
                f"capture_zero: got {len(sink)} of {n_frames} frames from {self.config.port} "
                f"in {timeout_s:.1f} s; is the board streaming? ({why})"
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
        self._parser.reset()
        self._scans.reset()
        self._converter = ScanConverter(self._calibration, cfg)  # compiled before the first scan
        self._reader.open(cfg)  # missing port or no permission: raise now, by name
        self._running = True
        self._reader.start()
        try:
            if self.wait_for_frame(self._scans.published_seq, cfg.connect_timeout_s) is None:
                raise self._reader.no_frame_error(cfg.connect_timeout_s)
            if cfg.zero_on_connect_frames:
                self.capture_zero(cfg.zero_on_connect_frames)
        except BaseException:
            self.disconnect()
            raise
        log.info("tactile board streaming on %s at %d baud", cfg.port, cfg.baudrate)

    def disconnect(self) -> None:
        self._reader.stop()
        self._running = False

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
            raise StaleDataError(f"{e} [{self._reader.diagnosis(self._running)}]") from None

    def stats(self) -> dict[str, int]:
        s = self._parser.stats.as_dict()
        s.update(self._counters)
        return s

    def status(self) -> dict[str, Any]:
        s = Device.status(self)
        reader = self._reader
        s.update(port=self.config.port, baudrate=self.config.baudrate, link=reader.link)
        if reader.link_error:
            s["link_error"] = reader.link_error
        s.update(self.stats())
        return s

    # -- hooks for simulation ---------------------------------------------------

    def _truth_for_wire_seq(self, wire_seq: int) -> GraspTruth | None:
        """Ground truth of a frame: a real board has none; a simulated one overrides."""
        return None

    # -- the stream ---------------------------------------------------------------

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
        self._scans.accept(packet, t_ns)

    def _on_scan(self, seq: int, wire_seq: int, payloads: bytes, t_ns: int) -> None:
        """Both pads' count bytes, pad 0 first: published raw, in newtons when read."""
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
