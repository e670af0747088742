"""LinkGlide's six Feetech STS servos, through feetech-servo-sdk used as it is.

What the driver adds to the SDK, and why:

- Safety first: goals outside the calibrated limits are refused before any
  byte is built (``ServoBus.write_goals``); torque goes off on ``disconnect``
  and on every fatal error, so a failing bus leaves the palm free.
- One lock per port: the SDK's ``is_using`` flag is not thread-safe, and the
  node's control loop and a monitor may share the bus.
- Results are always checked: a ``GroupSyncRead`` whose servo did not answer
  returns 0 for it with no error unless ``txRxPacket``'s result is read.
- A corrupt or missing status packet is retried (``retries``) after the line
  is drained (the SDK's ``clearPort`` flushes output only, so stale replies
  would otherwise be read as the next answer). A silent servo costs one
  reply window per attempt: the SDK's 34 ms (twice a 16 ms USB latency
  timer, plus 2 ms), or ``reply_timeout_ms`` when set.
- Errors name what to check: which ids did not answer, the port, the baud.
- One process on the bus at a time: the port is locked (``flock``) while
  open, so a second opener (``deepxpalm palm lift`` or ``calibrate`` beside
  a running node) is refused with who holds it, instead of interleaving its
  packets with the node's.
- The 60 Hz goal write of all six servos is laid out once
  (``sync_write.SyncWritePacket``, the SDK's bytes exactly) and sent through
  the SDK's port handler; rebuilding it with ``GroupSyncWrite`` cost about
  50 us a write on a cold core. Writes to some servos only, and every other
  instruction, go through the SDK.

Counts, not angles: the operator node converts angles with the calibration
(``LinkGlideCalibration.angles_to_counts``) and this bus checks them again.
"""

from __future__ import annotations

import fcntl
import logging
import os
import select
import termios
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

import scservo_sdk as sdk
import serial

from common.config import param
from common.devices import Device
from common.errors import (
    ConfigError,
    DeviceAlreadyConnectedError,
    DeviceError,
    DeviceTimeoutError,
    ProtocolError,
)
from common.preflight import Finding, PreflightContext, serial_findings
from operator_side.servos.base import ServoBus
from operator_side.servos.calibration import LinkGlideCalibration, load_calibration
from operator_side.servos.limits import check_goals
from operator_side.servos.sts_registers import (
    ACCELERATION,
    GOAL_POSITION,
    GOAL_SPEED,
    MODEL_NUMBERS,
    PRESENT_POSITION,
    TORQUE_ENABLE,
    describe_error,
)
from operator_side.servos.sync_write import SyncWritePacket

log = logging.getLogger(__name__)

#: the rates PortHandler.setBaudRate accepts; any other returns False
SDK_BAUD_RATES = (4800, 9600, 14400, 19200, 38400, 57600, 115200, 128000, 250000, 500000, 1000000)
_PORT_HINT = "list adapters with `ls -l /dev/serial/by-id` and set `port`"
#: what pyserial raises when the adapter disappears mid-transaction
_IO_ERRORS = (OSError, serial.SerialException, termios.error)


@dataclass
class FeetechConfig:
    port: str = param("/dev/ttyUSB0", "the bus adapter; prefer its /dev/serial/by-id/... name")
    baudrate: int = param(1_000_000, "STS servos ship at 1 Mbaud; must be one the SDK accepts")
    ids: tuple[int, ...] = param((1, 2, 3, 4, 5, 6), "linkage n uses ids 2n+1 and 2n+2")
    # param() is this project's dataclasses.field; it copies mutable defaults.
    calibration: LinkGlideCalibration = param(
        LinkGlideCalibration(), "zero, direction and limits, used when calibration_file is unset"
    )
    calibration_file: Path | None = param(
        None, "TOML written by `deepxpalm calibrate`; overrides the inline calibration"
    )
    retries: int = param(2, "extra attempts after a corrupt or missing reply (one window each)")
    reply_timeout_ms: float | None = param(
        None,
        "how long to wait for a status packet; unset = the SDK's 34 ms. Raise it for an "
        "adapter whose USB latency timer is above 16 ms",
    )
    protocol_end: int = param(0, "0 = STS (little-endian), 1 = SCS; one per process (SDK global)")
    expected_model: int | None = param(
        None, "refuse servos with another model number (777 = STS3215); unset = any"
    )
    torque_on_connect: bool = param(
        True, "hold the present pose (clipped to the limits) with torque on after connect"
    )
    goal_speed: int | None = param(
        None, "servo speed limit written at connect, counts/s (0 = max); unset = leave it"
    )
    acceleration: int | None = param(
        None, "servo acceleration written at connect (x100 counts/s^2); unset = leave it"
    )

    def __post_init__(self) -> None:
        if self.baudrate not in SDK_BAUD_RATES:
            raise ValueError(
                f"baudrate {self.baudrate} is not one feetech-servo-sdk accepts: {SDK_BAUD_RATES}"
            )
        if not self.ids or len(set(self.ids)) != len(self.ids):
            raise ValueError(f"ids must be a non-empty list without repeats, not {self.ids}")
        if any(not 0 <= i <= 0xFC for i in self.ids):
            raise ValueError(f"servo ids must be in 0..252, not {self.ids}")
        if self.retries < 0:
            raise ValueError("retries must not be negative")
        if self.reply_timeout_ms is not None and not 1.0 <= self.reply_timeout_ms <= 1000.0:
            raise ValueError(f"reply_timeout_ms = {self.reply_timeout_ms} is not in 1..1000")
        if self.protocol_end not in (0, 1):
            raise ValueError("protocol_end must be 0 (STS) or 1 (SCS)")
        for name in ("goal_speed", "acceleration"):
            v = getattr(self, name)
            if v is not None and not 0 <= v <= (0xFF if name == "acceleration" else 0xFFFF):
                raise ValueError(f"{name} = {v} is out of the register's range")


#: Longest one read waits for a reply's bytes before the SDK's loop looks at its clock again.
_READ_WAIT_S = 0.005


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


class _WaitingPort(sdk.PortHandler):
    """The SDK's port, waiting for a reply in ``select`` instead of spinning on ``read``.

    The SDK opens the line with ``timeout=0`` and loops on ``read`` until its
    reply window closes: a core spent per transaction, the GIL held in 5 ms
    turns, and every other thread of the process (the servo simulator's, in
    the demo) starved meanwhile, so a reply can miss its window only because
    its reader was spinning. Here each read first waits for bytes in
    ``select`` (the GIL released), at most ``_READ_WAIT_S`` or what is left of
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
            wait_s = min(_READ_WAIT_S, left_ms / 1e3)
            if wait_s > 0:
                select.select([ser.fileno()], [], [], wait_s)
        return ser.read(length)


class FeetechServoBus(ServoBus):
    """Goal positions in one sync write per call; present positions by sync read."""

    Config = FeetechConfig

    def __init__(self, config: FeetechConfig | None = None) -> None:
        self.config = config or FeetechConfig()
        self._lock = threading.RLock()  # the SDK port's own lock (is_using is not thread-safe)
        self._port: sdk.PortHandler | None = None
        self._ph: Any = None
        self._calibration: LinkGlideCalibration | None = None
        self._fault: str | None = None
        self._torque = False
        self._counters = {
            "sync_writes": 0,
            "sync_reads": 0,
            "retries": 0,
            "rx_corrupt": 0,
            "rx_timeout": 0,
            "faults": 0,
        }
        self.last_write_s = 0.0
        # the goal write of every servo, laid out once (sync_write.py: the SDK's bytes)
        self._goal_ids = tuple(self.config.ids)
        self._goal_id_set = frozenset(self._goal_ids)
        self._goal_packet = SyncWritePacket(
            self._goal_ids, GOAL_POSITION.address, big_endian=self.config.protocol_end == 1
        )
        self.last_read_s = 0.0

    # -- lifecycle ----------------------------------------------------------------

    def _preflight(self, context: PreflightContext) -> list[Finding]:
        return serial_findings(self.config.port, self.config.baudrate, context)

    def _location(self) -> str:
        return f"on {self.config.port} at {self.config.baudrate} baud"

    @property
    def is_connected(self) -> bool:
        return self._port is not None

    @property
    def calibration(self) -> LinkGlideCalibration | None:
        return self._calibration

    @property
    def fault(self) -> str | None:
        """Why the bus stopped (torque is off), or None while it is healthy."""
        return self._fault

    def connect(self, first_goals: Mapping[int, int] | None = None) -> None:
        """Open, ping every servo, read where they are, and hold them there (torque on).

        ``first_goals`` (every servo's, checked against the limits): written with
        torque on as the port opens, before any reply is awaited, and held
        instead of the present pose. The palm's lift wants its pose on the bus
        first and the checks after: eight round trips, each a reply window on a
        slow bus, would keep the linkages on the palm meanwhile.
        """
        if self._port is not None:
            raise DeviceAlreadyConnectedError(f"servo bus on {self.config.port} is connected")
        cfg = self.config
        self._calibration = self.configured_calibration()
        known = {s.id for s in self._calibration.servos}
        if not set(cfg.ids) <= known:
            raise ConfigError(f"servo ids {sorted(set(cfg.ids) - known)} have no calibration")
        first = None if first_goals is None else check_goals(self._calibration, first_goals)
        if first is not None and first.keys() != set(cfg.ids):
            raise ConfigError(f"first goals for ids {sorted(first)}, the bus has {list(cfg.ids)}")
        self._fault = None
        self._open()
        try:
            if first is not None:  # sync writes are not answered: nothing is waited for
                self._write_speed_and_acceleration()
                self._sync_write(GOAL_POSITION.address, 2, first)
                self._sync_write(TORQUE_ENABLE.address, 1, dict.fromkeys(cfg.ids, 1))
            self._ping_all()
            present = self.read_positions()
            if first is not None:
                self.set_torque(True)  # read back: a limp palm is not 'on'
            else:
                self._write_speed_and_acceleration()
                if cfg.torque_on_connect:
                    self._hold(present)
        except BaseException:
            self._shutdown()
            raise
        log.info("servo bus on %s: ids %s answered", cfg.port, list(cfg.ids))

    def configured_calibration(self) -> LinkGlideCalibration:
        """The calibration ``connect`` enforces: ``calibration_file``'s, else the config's."""
        cfg = self.config
        return load_calibration(cfg.calibration_file) if cfg.calibration_file else cfg.calibration

    def _write_speed_and_acceleration(self) -> None:
        cfg = self.config
        if cfg.goal_speed is not None:
            self._sync_write(GOAL_SPEED.address, 2, dict.fromkeys(cfg.ids, cfg.goal_speed))
        if cfg.acceleration is not None:
            self._sync_write(ACCELERATION.address, 1, dict.fromkeys(cfg.ids, cfg.acceleration))

    def disconnect(self) -> None:
        """Torque off (best effort), then close. Safe to call in any state."""
        self._shutdown()

    def reconnect(self) -> None:
        """After a fault or a replug: close, open, ping, hold."""
        self._shutdown()
        self.connect()

    # -- ServoBus -------------------------------------------------------------------

    def _write_goals(self, checked: dict[int, int]) -> None:
        """One sync write of every goal (``write_goals`` has checked them against the limits)."""
        self._require_healthy()
        t = time.perf_counter()
        if checked.keys() == self._goal_id_set:  # every servo: the control loop's write
            self._write_packet(self._goal_packet.build([checked[i] for i in self._goal_ids]))
        else:
            unknown = set(checked) - self._goal_id_set
            if unknown:
                raise ConfigError(
                    f"servo ids {sorted(unknown)} are not on this bus {self.config.ids}"
                )
            self._sync_write(GOAL_POSITION.address, 2, checked)
        self.last_write_s = time.perf_counter() - t

    def read_positions(self) -> dict[int, int]:
        """Present positions of every servo, or an error naming the one that failed."""
        self._require_healthy()
        t = time.perf_counter()
        values = self._sync_read(PRESENT_POSITION.address, 2)
        self.last_read_s = time.perf_counter() - t
        return values

    def set_torque(self, enabled: bool) -> None:
        """All servos at once; torque on is read back, because a limp palm is not 'on'."""
        self._require_healthy()
        value = 1 if enabled else 0
        self._sync_write(TORQUE_ENABLE.address, 1, dict.fromkeys(self.config.ids, value))
        if enabled:
            state = self._sync_read(TORQUE_ENABLE.address, 1)
            off = [sid for sid, v in state.items() if v != 1]
            if off:
                self._raise_fault(DeviceError, f"servos {off} did not enable torque")
        self._torque = enabled

    def read_register(self, address: int, size: int) -> dict[int, int]:
        """Any register of every servo (monitoring: load, temperature, voltage)."""
        self._require_healthy()
        return self._sync_read(address, size)

    # -- status ---------------------------------------------------------------------

    def stats(self) -> dict[str, int]:
        return dict(self._counters)

    def status(self) -> dict[str, Any]:
        s = Device.status(self)
        s.update(
            port=self.config.port,
            baudrate=self.config.baudrate,
            ids=list(self.config.ids),
            torque=self._torque,
            fault=self._fault,
            last_write_us=round(self.last_write_s * 1e6),
            last_read_us=round(self.last_read_s * 1e6),
        )
        s.update(self._counters)
        return s

    # -- internals ------------------------------------------------------------------

    def _require_healthy(self) -> None:
        self.require_connected()
        if self._fault is not None:
            raise DeviceError(
                f"servo bus on {self.config.port} stopped after a fault ({self._fault}); "
                "torque is off. Fix the cause, then call reconnect()"
            )

    def _open(self) -> None:
        cfg = self.config
        if not os.path.exists(cfg.port):
            raise DeviceError(f"servo bus port {cfg.port} does not exist: {_PORT_HINT}")
        port = _WaitingPort(cfg.port, cfg.reply_timeout_ms)
        port.baudrate = cfg.baudrate
        try:
            ok = port.setBaudRate(cfg.baudrate)
        except serial.SerialException as e:
            if "Permission denied" in str(e):
                raise DeviceError(
                    f"no permission to open {cfg.port}: add yourself to the dialout group "
                    "(`sudo usermod -aG dialout $USER`, then log in again)"
                ) from e
            raise DeviceError(f"cannot open servo bus port {cfg.port}: {e}; {_PORT_HINT}") from e
        if not ok:
            raise ConfigError(f"feetech-servo-sdk refused baudrate {cfg.baudrate}")
        self._ph = sdk.PacketHandler(cfg.protocol_end)
        self._port = port

    def _shutdown(self) -> None:
        port = self._port
        if port is None:
            return
        with self._lock:
            try:
                self._torque_off_best_effort()
            finally:
                try:
                    port.closePort()
                except (OSError, serial.SerialException) as e:
                    log.debug("closing %s: %s", self.config.port, e)
                self._port = None
                self._torque = False

    def _torque_off_best_effort(self) -> None:
        try:
            self._sync_write(TORQUE_ENABLE.address, 1, dict.fromkeys(self.config.ids, 0))
            self._torque = False
        except DeviceError as e:
            log.error("could not turn servo torque off on %s: %s", self.config.port, e)

    def _raise_fault(self, kind: type[DeviceError], message: str) -> NoReturn:
        """Torque off, remember why, and raise: the bus refuses work until reconnect()."""
        full = f"servo bus on {self.config.port}: {message}"
        self._counters["faults"] += 1
        if self._fault is None:
            self._fault = message
            log.error("%s; turning torque off", full)
            self._torque_off_best_effort()
        raise kind(f"{full}; torque is off. Fix the cause, then call reconnect()")

    def _ping_all(self) -> None:
        cfg = self.config
        missing: list[int] = []
        wrong: list[str] = []
        for sid in cfg.ids:
            model, result, error = self._with_retries(
                lambda sid=sid: self._ph.ping(self._port, sid)
            )
            if result != sdk.COMM_SUCCESS:
                missing.append(sid)
                continue
            if error:
                log.warning("servo %d reports: %s", sid, describe_error(error) or error)
            if cfg.expected_model is not None and model != cfg.expected_model:
                wrong.append(f"{sid} is model {model} ({MODEL_NUMBERS.get(model, 'unknown')})")
        if missing:
            answered = [i for i in cfg.ids if i not in missing]
            if not answered:
                raise DeviceTimeoutError(
                    f"no servo answered on {cfg.port} at {cfg.baudrate} baud "
                    f"(ids {list(cfg.ids)}): "
                    "are the servos powered (their own 6-12 V supply; USB does not power them)? "
                    "TX/RX wired to the adapter? The baud rate right (STS ship at 1000000)?"
                )
            raise DeviceTimeoutError(
                f"servos {missing} did not answer on {cfg.port} (ids {answered} did): check "
                "their cables and that their ids are set (one servo at a time on the bus)"
            )
        if wrong:
            raise ProtocolError(
                f"unexpected servo model on {cfg.port}: {'; '.join(wrong)}; "
                f"expected_model is {cfg.expected_model}"
            )

    def _hold(self, present: Mapping[int, int]) -> None:
        """Goal = present pose (clipped into the limits), then torque on: no jump."""
        assert self._calibration is not None
        by_id = {s.id: s for s in self._calibration.servos}
        goals = {}
        for sid, counts in present.items():
            s = by_id[sid]
            goals[sid] = min(max(counts, s.min_counts), s.max_counts)
            if goals[sid] != counts:
                log.warning(
                    "servo %d is at %d, outside its limits [%d, %d]: it will move to %d",
                    sid,
                    counts,
                    s.min_counts,
                    s.max_counts,
                    goals[sid],
                )
        self._sync_write(GOAL_POSITION.address, 2, check_goals(self._calibration, goals))
        self.set_torque(True)

    def _with_retries(self, call: Any) -> Any:
        """Run an SDK transaction, again after a corrupt or missing reply."""
        out = None
        seen: list[str] = []  # each attempt's outcome and how long it took, for the error
        unanswered = False  # the last try's reply is missing, or was another request's
        for attempt in range(self.config.retries + 1):
            t0 = time.monotonic()
            with self._lock:
                if attempt:
                    self._counters["retries"] += 1
                    self._drain(late_window_s=self._reply_window_s() if unanswered else 0.0)
                try:
                    out = call()
                except _IO_ERRORS as e:
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
        port = self._port
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
        self._raise_fault(
            DeviceError,
            f"the adapter vanished ({type(error).__name__}: {error}); "
            f"replug it and check `ls -l /dev/serial/by-id`",
        )

    def _write_packet(self, packet: bytearray) -> None:
        """A goal sync write built by ``SyncWritePacket``, out as the SDK's txPacket sends it."""
        port = self._port
        if port is None:
            raise DeviceError(f"servo bus on {self.config.port} is not open")
        with self._lock:
            try:
                port.clearPort()
                written = port.writePort(packet)
            except _IO_ERRORS as e:
                self._lost(e)
        if written != len(packet):
            self._raise_fault(
                DeviceError, f"sync write failed: {written} of {len(packet)} bytes written"
            )
        self._counters["sync_writes"] += 1

    def _sync_write(self, address: int, size: int, values: Mapping[int, int]) -> None:
        if self._port is None:
            raise DeviceError(f"servo bus on {self.config.port} is not open")
        with self._lock:
            group = sdk.GroupSyncWrite(self._port, self._ph, address, size)
            for sid, value in values.items():
                data = [sdk.SCS_LOBYTE(value), sdk.SCS_HIBYTE(value)] if size == 2 else [value]
                group.addParam(sid, data)
            try:
                result = group.txPacket()
            except _IO_ERRORS as e:
                self._lost(e)
        if result != sdk.COMM_SUCCESS:
            self._raise_fault(DeviceError, f"sync write failed: {self._ph.getTxRxResult(result)}")
        if address == GOAL_POSITION.address:
            self._counters["sync_writes"] += 1

    def _sync_read(self, address: int, size: int) -> dict[int, int]:
        ids = list(self.config.ids)
        group: Any = None

        def transaction() -> int:
            nonlocal group
            self._port.ser.reset_input_buffer()  # type: ignore[union-attr]
            group = sdk.GroupSyncRead(self._port, self._ph, address, size)
            for sid in ids:
                group.addParam(sid)
            return group.txRxPacket()

        result = self._with_retries(transaction)
        self._counters["sync_reads"] += 1
        if result != sdk.COMM_SUCCESS:
            # The SDK stops at the first servo that failed: its data stays empty.
            failed = next((sid for sid in ids if not group.data_dict.get(sid)), None)
            what = self._ph.getTxRxResult(result)
            kind = DeviceTimeoutError if result == sdk.COMM_RX_TIMEOUT else ProtocolError
            self._raise_fault(
                kind,
                f"servo {failed} did not answer a read of address {address} after "
                f"{self.config.retries + 1} attempts ({what}): check its cable and power",
            )
        values = {}
        for sid in ids:
            if not group.isAvailable(sid, address, size):
                self._raise_fault(ProtocolError, f"servo {sid} sent no data for address {address}")
            values[sid] = group.getData(sid, address, size)
        return values
