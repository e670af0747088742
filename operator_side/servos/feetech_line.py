"""The line to the servos: the SDK's port, waiting in ``select``, and its transactions.

One lock per port (the SDK's ``is_using`` flag is not thread-safe); every
result checked; a corrupt or missing reply retried after the line is
drained; an adapter that vanishes, or a bus that fails, handed to the bus's
fault (``fail``: torque off, and no more work until a reconnect). The port
is locked (``flock``) while open: one process on the bus at a time.
"""

from __future__ import annotations

import fcntl
import logging
import os
import select
import termios
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, NoReturn

import scservo_sdk as sdk
import serial

from common.errors import ConfigError, DeviceError, DeviceTimeoutError, ProtocolError
from operator_side.servos.feetech_config import FeetechConfig
from operator_side.servos.sts_registers import GOAL_POSITION

log = logging.getLogger(__name__)

PORT_HINT = "list adapters with `ls -l /dev/serial/by-id` and set `port`"
#: what pyserial raises when the adapter disappears mid-transaction
IO_ERRORS = (OSError, serial.SerialException, termios.error)

#: Longest one read waits for a reply's bytes before the SDK's loop looks at its clock again.
READ_WAIT_S = 0.005


class PortBusyError(DeviceError):
    """Another process holds the servo bus's port (its lock); nothing was sent."""


def port_holders(port: str) -> list[str]:
    """``pid (command line)`` of every other process with ``port`` open that we may see."""
    target = os.path.realpath(port)
    found = []
    for pid in filter(str.isdigit, os.listdir("/proc")):
        if int(pid) == os.getpid():
            continue
        try:
            fds = os.listdir(f"/proc/{pid}/fd")
            if not any(os.readlink(f"/proc/{pid}/fd/{fd}") == target for fd in fds):
                continue
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:  # gone, or another user's: not ours to see
            continue
        found.append(f"{pid} ({cmd.strip()[:120]})")
    return found


class WaitingPort(sdk.PortHandler):
    """The SDK's port, waiting for a reply in ``select`` instead of spinning on ``read``.

    The SDK opens the line with ``timeout=0`` and loops on ``read`` until its
    reply window closes: a core spent per transaction, the GIL held in 5 ms
    turns, and every other thread of the process (the servo simulator's, in
    the demo) starved meanwhile, so a reply can miss its window only because
    its reader was spinning. Here each read first waits for bytes in
    ``select`` (the GIL released), at most ``READ_WAIT_S`` or what is left of
    the window. The window runs on the monotonic clock (the SDK's uses
    ``time.time``, which a clock step moves); ``reply_timeout_ms`` replaces
    the SDK's 34 ms when set.
    """

    def __init__(self, port_name: str, reply_timeout_ms: float | None = None) -> None:
        super().__init__(port_name)
        self.reply_timeout_ms = reply_timeout_ms

    def setupPort(self, cflag_baud: int) -> bool:  # the SDK calls it by this name
        """The SDK's open, then the port's lock: refused while another process holds it."""
        ok = super().setupPort(cflag_baud)
        try:
            fcntl.flock(self.ser.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            self.ser.close()
            self.is_open = False
            holders = port_holders(self.port_name)
            raise PortBusyError(
                f"servo bus port {self.port_name} is in use by another process"
                + (f" (open in pid {', '.join(holders)})" if holders else "")
                + ": stop the operator node first (`systemctl stop deepxpalm-operator`, "
                "which lifts the palm itself), or end a frozen one with `kill -9 PID`"
            ) from None
        return ok

    def getCurrentTime(self) -> float:  # the SDK calls it by this name; milliseconds
        return time.monotonic() * 1e3

    def setPacketTimeout(self, packet_length: int) -> None:  # the SDK calls it by this name
        if self.reply_timeout_ms is None:
            super().setPacketTimeout(packet_length)
            return
        self.packet_start_time = self.getCurrentTime()
        self.packet_timeout = self.tx_time_per_byte * packet_length + self.reply_timeout_ms

    def readPort(self, length: int) -> bytes:  # the SDK calls it by this name
        ser = self.ser
        if not ser.in_waiting and self.packet_timeout > 0:
            left_ms = self.packet_timeout - (self.getCurrentTime() - self.packet_start_time)
            wait_s = min(READ_WAIT_S, left_ms / 1e3)
            if wait_s > 0:
                select.select([ser.fileno()], [], [], wait_s)
        return ser.read(length)


class FeetechLine:
    """The open port (``port``) and the SDK's packet handler, while the bus is connected.

    ``fail(kind, message)`` is the bus's fault: it turns torque off, remembers
    why and raises ``kind``; ``counters`` are the bus's.
    """

    def __init__(
        self,
        counters: dict[str, int],
        fail: Callable[[type[DeviceError], str], NoReturn],
    ) -> None:
        self.lock = threading.RLock()  # the SDK port's own lock (is_using is not thread-safe)
        self.port: WaitingPort | None = None
        self.config = FeetechConfig()
        self._ph: Any = None
        self._counters = counters
        self._fail = fail

    def open(self, cfg: FeetechConfig) -> None:
        """Open ``cfg.port`` at its baud rate (and take its lock), or say what to check."""
        self.config = cfg
        if not os.path.exists(cfg.port):
            raise DeviceError(f"servo bus port {cfg.port} does not exist: {PORT_HINT}")
        port = WaitingPort(cfg.port, cfg.reply_timeout_ms)
        port.baudrate = cfg.baudrate
        try:
            ok = port.setBaudRate(cfg.baudrate)
        except serial.SerialException as e:
            if "Permission denied" in str(e):
                raise DeviceError(
                    f"no permission to open {cfg.port}: add yourself to the dialout group "
                    "(`sudo usermod -aG dialout $USER`, then log in again)"
                ) from e
            raise DeviceError(f"cannot open servo bus port {cfg.port}: {e}; {PORT_HINT}") from e
        if not ok:
            raise ConfigError(f"feetech-servo-sdk refused baudrate {cfg.baudrate}")
        self._ph = sdk.PacketHandler(cfg.protocol_end)
        self.port = port

    def close(self) -> None:
        """Close the port (the caller has turned torque off)."""
        port, self.port = self.port, None
        if port is None:
            return
        try:
            port.closePort()
        except (OSError, serial.SerialException) as e:
            log.debug("closing %s: %s", self.config.port, e)

    def ping(self, sid: int) -> tuple[int, int, int]:
        """(model, result, error) of one servo's ping, retried."""
        return self.with_retries(lambda: self._ph.ping(self.port, sid))

    def with_retries(self, call: Any) -> Any:
        """Run an SDK transaction, again after a corrupt or missing reply."""
        out = None
        seen: list[str] = []  # each attempt's outcome and how long it took, for the error
        unanswered = False  # the last try's reply is missing, or was another request's
        for attempt in range(self.config.retries + 1):
            t0 = time.monotonic()
            with self.lock:
                if attempt:
                    self._counters["retries"] += 1
                    self._drain(late_window_s=self._reply_window_s() if unanswered else 0.0)
                try:
                    out = call()
                except IO_ERRORS as e:
                    self._lost(e)
                except IndexError:  # the SDK indexes past a short, garbled reply
                    out = None
            took = f"{(time.monotonic() - t0) * 1e3:.0f} ms"
            unanswered = out is None or (isinstance(out, tuple) and out[1] == sdk.COMM_RX_TIMEOUT)
            if out is None:
                self._counters["rx_corrupt"] += 1
                seen.append(f"short reply ({took})")
                continue
            result = out[1] if isinstance(out, tuple) else out
            if result == sdk.COMM_SUCCESS:
                return out
            if result == sdk.COMM_RX_CORRUPT:
                self._counters["rx_corrupt"] += 1
                seen.append(f"corrupt ({took})")
            elif result == sdk.COMM_RX_TIMEOUT:
                self._counters["rx_timeout"] += 1
                seen.append(f"no reply ({took})")
            else:
                return out  # busy/tx failure: retrying the same bytes will not help
        if out is None:
            raise ProtocolError(
                f"servo bus {self.config.port}: replies stay garbled after "
                f"{self.config.retries + 1} tries ({', '.join(seen)}): noise on the line, "
                "or a wrong protocol_end?"
            )
        return out

    def _drain(self, late_window_s: float = 0.0) -> None:
        """Wait for the line to go quiet, then drop what arrived (late or stale replies).

        After a reply that never came (or came for another request), wait up
        to ``late_window_s`` for it to turn up late: a reply arriving after
        the next request went out would be taken as that request's (the SDK
        matches replies by servo id only), and every try after it would read
        the one before's reply.
        """
        port = self.port
        assert port is not None
        start = time.monotonic()
        deadline = start + max(0.02, late_window_s)
        quiet_since = start
        dropped = False
        while (now := time.monotonic()) < deadline:
            if port.ser.in_waiting:
                port.ser.reset_input_buffer()
                quiet_since, dropped = now, True
            elif now - quiet_since > 0.002 and (dropped or now - start >= late_window_s):
                break
            time.sleep(0.0005)
        port.ser.reset_input_buffer()

    def _reply_window_s(self) -> float:
        """How long a reply may take: ``reply_timeout_ms``, or the SDK's 34 ms."""
        ms = self.config.reply_timeout_ms
        return (ms if ms is not None else 2.0 * sdk.port_handler.LATENCY_TIMER + 2.0) / 1e3

    def _lost(self, error: BaseException) -> NoReturn:
        self._fail(
            DeviceError,
            f"the adapter vanished ({type(error).__name__}: {error}); "
            f"replug it and check `ls -l /dev/serial/by-id`",
        )

    def write_packet(self, packet: bytearray) -> None:
        """A goal sync write built by ``SyncWritePacket``, out as the SDK's txPacket sends it."""
        port = self.port
        if port is None:
            raise DeviceError(f"servo bus on {self.config.port} is not open")
        with self.lock:
            try:
                port.clearPort()
                written = port.writePort(packet)
            except IO_ERRORS as e:
                self._lost(e)
        if written != len(packet):
            self._fail(DeviceError, f"sync write failed: {written} of {len(packet)} bytes written")
        self._counters["sync_writes"] += 1

    def sync_write(self, address: int, size: int, values: Mapping[int, int]) -> None:
        if self.port is None:
            raise DeviceError(f"servo bus on {self.config.port} is not open")
        with self.lock:
            group = sdk.GroupSyncWrite(self.port, self._ph, address, size)
            for sid, value in values.items():
                data = [sdk.SCS_LOBYTE(value), sdk.SCS_HIBYTE(value)] if size == 2 else [value]
                group.addParam(sid, data)
            try:
                result = group.txPacket()
            except IO_ERRORS as e:
                self._lost(e)
        if result != sdk.COMM_SUCCESS:
            self._fail(DeviceError, f"sync write failed: {self._ph.getTxRxResult(result)}")
        if address == GOAL_POSITION.address:
            self._counters["sync_writes"] += 1

    def sync_read(self, address: int, size: int) -> dict[int, int]:
        ids = list(self.config.ids)
        group: Any = None

        def transaction() -> int:
            nonlocal group
            self.port.ser.reset_input_buffer()  # type: ignore[union-attr]
            group = sdk.GroupSyncRead(self.port, self._ph, address, size)
            for sid in ids:
                group.addParam(sid)
            return group.txRxPacket()

        result = self.with_retries(transaction)
        self._counters["sync_reads"] += 1
        if result != sdk.COMM_SUCCESS:
            # The SDK stops at the first servo that failed: its data stays empty.
            failed = next((sid for sid in ids if not group.data_dict.get(sid)), None)
            what = self._ph.getTxRxResult(result)
            kind = DeviceTimeoutError if result == sdk.COMM_RX_TIMEOUT else ProtocolError
            self._fail(
                kind,
                f"servo {failed} did not answer a read of address {address} after "
                f"{self.config.retries + 1} attempts ({what}): check its cable and power",
            )
        values = {}
        for sid in ids:
            if not group.isAvailable(sid, address, size):
                self._fail(ProtocolError, f"servo {sid} sent no data for address {address}")
            values[sid] = group.getData(sid, address, size)
        return values
