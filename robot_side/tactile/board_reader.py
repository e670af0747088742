"""The tactile board's port and the thread that reads it.

The reader thread owns the port and the stream parser: bytes in, packets to
the scan pairing. A board that vanishes from the bus (unplugged) is reopened
by name until it comes back (``auto_reconnect``). When frames are missing,
``diagnosis`` says why: the board went silent, sends only garbage (a wrong
baud rate), or vanished.
"""

from __future__ import annotations

import logging
import os
import select
import threading

import serial

from common.clocks.clock import now_ns
from common.errors import ConfigError, DeviceError, DeviceTimeoutError, ProtocolError
from robot_side.tactile.scans import ScanPairing
from robot_side.tactile.serial_config import SerialTactileConfig
from robot_side.tactile.wire import StreamParser

log = logging.getLogger(__name__)

PORT_HINT = "list the connected boards with `ls -l /dev/serial/by-id` and set `port`"
#: bytes taken per read: everything a line at 921600 baud delivers in 40 ms
READ_SIZE = 4096


def open_board_port(cfg: SerialTactileConfig) -> serial.Serial:
    """The board's port, opened; an error that names what to check."""
    if not os.path.exists(cfg.port):
        raise DeviceError(f"tactile board port {cfg.port} does not exist: {PORT_HINT}")
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
        raise DeviceError(f"cannot open tactile board port {cfg.port}: {e}; {PORT_HINT}") from e


class BoardReader:
    """The open port (while connected), its reader thread and the link's state.

    ``link`` is closed, open or down (the board vanished); counts
    ``disconnects`` and ``reconnects`` into ``counters``.
    """

    def __init__(self, parser: StreamParser, scans: ScanPairing, counters: dict[str, int]) -> None:
        self._parser = parser
        self._scans = scans
        self._counters = counters
        self.config = SerialTactileConfig()  # the driver's, as it was at open()
        self._ser: serial.Serial | None = None
        self._ser_lock = threading.Lock()  # open/close races between reader and stop()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.link = "closed"  # closed | open | down
        self.link_error: str | None = None
        self.link_down_ns = 0
        self.last_byte_ns = 0
        self.last_packet_ns = 0

    def open(self, cfg: SerialTactileConfig) -> None:
        """Open ``cfg.port`` (a missing port or no permission raises now, by name)."""
        self.config = cfg
        self._ser = open_board_port(cfg)
        self.link = "open"
        self._stop.clear()

    def start(self) -> None:
        """The reader thread, reading until ``stop()``."""
        self._thread = threading.Thread(
            target=self._run, name=f"tactile-{os.path.basename(self.config.port)}", daemon=True
        )
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            if self._thread.is_alive():
                log.warning("tactile reader thread did not stop within 2 s")
        self._thread = None
        self._close_port()
        self.link = "closed"

    def _close_port(self) -> None:
        with self._ser_lock:
            ser, self._ser = self._ser, None
        if ser is not None:
            try:
                ser.close()
            except (OSError, serial.SerialException) as e:
                log.debug("closing %s: %s", self.config.port, e)

    def _run(self) -> None:
        cfg = self.config
        while not self._stop.is_set():
            ser = self._ser
            if ser is None:
                if not cfg.auto_reconnect:
                    self._stop.wait(cfg.read_timeout_s)
                    continue
                try:
                    opened = open_board_port(cfg)
                except (DeviceError, ConfigError) as e:
                    self.link_error = str(e)
                    self._stop.wait(cfg.reconnect_interval_s)
                    continue
                with self._ser_lock:
                    if self._stop.is_set():
                        opened.close()
                        break
                    self._ser = opened
                self._parser.reset()
                self._scans.reset()
                self.link = "open"
                self.link_error = None
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
                chunk = os.read(fd, READ_SIZE)
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
            self.last_byte_ns = t
            for packet in self._parser.feed(chunk):
                self.last_packet_ns = t
                self._scans.accept(packet, t)

    def _on_link_lost(self, error: BaseException) -> None:
        self._counters["disconnects"] += 1
        self.link = "down"
        self.link_down_ns = now_ns()
        self.link_error = f"{type(error).__name__}: {error}"
        self._close_port()
        log.error(
            "tactile board on %s vanished (%s); %s",
            self.config.port,
            error,
            "reopening it when it comes back" if self.config.auto_reconnect else "not reconnecting",
        )

    def diagnosis(self, running: bool) -> str:
        """One line on why frames are missing, for error messages."""
        cfg = self.config
        now = now_ns()
        if not running:
            return "not connected"
        if self.link == "down":
            down_ms = (now - self.link_down_ns) / 1e6
            again = "reopening it" if cfg.auto_reconnect else "auto_reconnect is off: reconnect()"
            return f"board on {cfg.port} vanished {down_ms:.0f} ms ago ({self.link_error}); {again}"
        st = self._parser.stats
        if self.last_byte_ns == 0:
            return (
                f"nothing received on {cfg.port} since it was opened: board powered and streaming?"
            )
        silent_ms = (now - self.last_byte_ns) / 1e6
        if silent_ms > 2 * 1000 / 120:
            return (
                f"board on {cfg.port} has sent nothing for {silent_ms:.0f} ms: it stopped streaming"
            )
        since_packet_ms = (now - self.last_packet_ns) / 1e6 if self.last_packet_ns else None
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

    def no_frame_error(self, waited_s: float) -> DeviceError:
        cfg = self.config
        st = self._parser.stats
        if self.link == "down":
            return DeviceError(
                f"tactile board on {cfg.port} vanished while connecting: {self.link_error}"
            )
        if st.bytes_in == 0:
            return DeviceTimeoutError(
                f"opened {cfg.port} at {cfg.baudrate} baud but the tactile board sent nothing in "
                f"{waited_s:.1f} s: is it powered and streaming? Is this the right port? "
                f"({PORT_HINT})"
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
