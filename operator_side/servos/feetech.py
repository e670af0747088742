"""LinkGlide's six Feetech STS servos, through feetech-servo-sdk used as it is.

What the driver adds to the SDK, and why:

- Safety first: goals outside the calibrated limits are refused before any
  byte is built (``ServoBus.write_goals``); torque goes off on ``disconnect``
  and on every fatal error, so a failing bus leaves the palm free.
- One lock per port: the SDK's ``is_using`` flag is not thread-safe, and the
  node's loop (its palm steps) and a monitor may share the bus.
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

The port and its transactions are ``feetech_line``'s, the settings
``feetech_config``'s; this module is the bus: connect, goals, reads, faults.

Counts, not angles: the operator node converts angles with the calibration
(``LinkGlideCalibration.angles_to_counts``) and this bus checks them again.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping
from typing import Any, NoReturn, TypeVar

import scservo_sdk as sdk

from common.devices.lifecycle import Device
from common.devices.preflight import Finding, PreflightContext, serial_findings
from common.errors import (
    ConfigError,
    DeviceAlreadyConnectedError,
    DeviceError,
    DeviceTimeoutError,
    ProtocolError,
)
from operator_side.servos.base import ServoBus
from operator_side.servos.calibration import LinkGlideCalibration, load_calibration
from operator_side.servos.feetech_config import SDK_BAUD_RATES, FeetechConfig
from operator_side.servos.feetech_line import FeetechLine, PortBusyError, port_holders
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

__all__ = [
    "SDK_BAUD_RATES",
    "FeetechConfig",
    "FeetechServoBus",
    "PortBusyError",
    "port_holders",
]

log = logging.getLogger(__name__)

#: between two rounds of pings to the servos that did not answer at connect
PING_AGAIN_S = 0.1
_T = TypeVar("_T")


class FeetechServoBus(ServoBus):
    """Goal positions in one sync write per call; present positions by sync read."""

    Config = FeetechConfig

    def __init__(self, config: FeetechConfig | None = None) -> None:
        self.config = config or FeetechConfig()
        self._calibration: LinkGlideCalibration | None = None
        self._fault: str | None = None
        self._connect_deadline: float | None = None  # set while connect() runs
        self._torque = False
        self._counters = {
            "sync_writes": 0,
            "sync_reads": 0,
            "retries": 0,
            "rx_corrupt": 0,
            "rx_timeout": 0,
            "faults": 0,
        }
        #: the port and its transactions, open while connected
        self._line = FeetechLine(self._counters, self._raise_fault)
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
        return self._line.port is not None

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
        if self._line.port is not None:
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
        self._line.open(cfg)
        self._connect_deadline = time.monotonic() + cfg.connect_timeout_s
        try:
            if first is not None:  # sync writes are not answered: nothing is waited for
                self._write_speed_and_acceleration()
                self._line.sync_write(GOAL_POSITION.address, 2, first)
                self._line.sync_write(TORQUE_ENABLE.address, 1, dict.fromkeys(cfg.ids, 1))
            self._ping_all(self._connect_deadline)
            present = self._until_connected(self.read_positions)
            if first is not None:  # read back: a limp palm is not 'on'
                self._until_connected(lambda: self.set_torque(True))
            else:
                self._write_speed_and_acceleration()
                if cfg.torque_on_connect:
                    self._hold(present)
        except BaseException:
            self._shutdown()
            raise
        finally:
            self._connect_deadline = None
        log.info("servo bus on %s: ids %s answered", cfg.port, list(cfg.ids))

    def configured_calibration(self) -> LinkGlideCalibration:
        """The calibration ``connect`` enforces: ``calibration_file``'s, else the config's."""
        cfg = self.config
        return load_calibration(cfg.calibration_file) if cfg.calibration_file else cfg.calibration

    def _write_speed_and_acceleration(self) -> None:
        cfg = self.config
        if cfg.goal_speed is not None:
            self._line.sync_write(GOAL_SPEED.address, 2, dict.fromkeys(cfg.ids, cfg.goal_speed))
        if cfg.acceleration is not None:
            self._line.sync_write(ACCELERATION.address, 1, dict.fromkeys(cfg.ids, cfg.acceleration))

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
        if checked.keys() == self._goal_id_set:  # every servo: a palm step's write
            self._line.write_packet(self._goal_packet.build([checked[i] for i in self._goal_ids]))
        else:
            unknown = set(checked) - self._goal_id_set
            if unknown:
                raise ConfigError(
                    f"servo ids {sorted(unknown)} are not on this bus {self.config.ids}"
                )
            self._line.sync_write(GOAL_POSITION.address, 2, checked)
        self.last_write_s = time.perf_counter() - t

    def read_positions(self) -> dict[int, int]:
        """Present positions of every servo, or an error naming the one that failed."""
        self._require_healthy()
        t = time.perf_counter()
        values = self._line.sync_read(PRESENT_POSITION.address, 2)
        self.last_read_s = time.perf_counter() - t
        return values

    def set_torque(self, enabled: bool) -> None:
        """All servos at once; torque on is read back, because a limp palm is not 'on'."""
        self._require_healthy()
        value = 1 if enabled else 0
        self._line.sync_write(TORQUE_ENABLE.address, 1, dict.fromkeys(self.config.ids, value))
        if enabled:
            state = self._line.sync_read(TORQUE_ENABLE.address, 1)
            off = [sid for sid, v in state.items() if v != 1]
            if off:
                self._raise_fault(DeviceError, f"servos {off} did not enable torque")
        self._torque = enabled

    def read_register(self, address: int, size: int) -> dict[int, int]:
        """Any register of every servo (monitoring: load, temperature, voltage)."""
        self._require_healthy()
        return self._line.sync_read(address, size)

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

    def _shutdown(self) -> None:
        line = self._line
        if line.port is None:
            return
        with line.lock:
            try:
                self._torque_off_best_effort()
            finally:
                line.close()
                self._torque = False

    def _torque_off_best_effort(self) -> None:
        try:
            self._line.sync_write(TORQUE_ENABLE.address, 1, dict.fromkeys(self.config.ids, 0))
            self._torque = False
        except DeviceError as e:
            log.error("could not turn servo torque off on %s: %s", self.config.port, e)

    def _raise_fault(self, kind: type[DeviceError], message: str) -> NoReturn:
        """Torque off, remember why, and raise: the bus refuses work until reconnect()."""
        full = f"servo bus on {self.config.port}: {message}"
        until = self._connect_deadline  # connecting: asked again until then (_until_connected)
        if kind is DeviceTimeoutError and until is not None and time.monotonic() < until:
            raise kind(f"{full} (while connecting)")
        self._counters["faults"] += 1
        if self._fault is None:
            self._fault = message
            log.error("%s; turning torque off", full)
            self._torque_off_best_effort()
        raise kind(f"{full}; torque is off. Fix the cause, then call reconnect()")

    def _until_connected(self, step: Callable[[], _T]) -> _T:
        """``step()`` again while a reply is missing and ``connect_timeout_s`` has not passed
        since the port opened (a bus just powered, a reply lost); past it, the fault stands."""
        while True:
            try:
                return step()
            except DeviceTimeoutError as e:
                if self._fault is not None:
                    raise
                log.info("%s; asking again", e)
                time.sleep(PING_AGAIN_S)

    def _ping_all(self, deadline: float) -> None:
        """Every servo answers a ping with the expected model; a servo still booting (or a
        reply a loaded machine lost) is pinged again until ``deadline``."""
        cfg = self.config
        models: dict[int, int] = {}
        rounds = 0
        while True:
            for sid in cfg.ids:
                if sid in models:
                    continue
                model, result, error = self._line.ping(sid)
                if result != sdk.COMM_SUCCESS:
                    continue
                models[sid] = model
                if error:
                    log.warning("servo %d reports: %s", sid, describe_error(error) or error)
            missing = [sid for sid in cfg.ids if sid not in models]
            if not missing or time.monotonic() >= deadline:
                break
            if rounds == 0:
                log.info("servos %s did not answer on %s; pinging them again", missing, cfg.port)
            rounds += 1
            time.sleep(PING_AGAIN_S)
        wrong = [
            f"{sid} is model {model} ({MODEL_NUMBERS.get(model, 'unknown')})"
            for sid, model in models.items()
            if cfg.expected_model is not None and model != cfg.expected_model
        ]
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
                f"servos {missing} did not answer on {cfg.port} in {cfg.connect_timeout_s:g} s "
                f"(ids {answered} did): check "
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
        self._line.sync_write(GOAL_POSITION.address, 2, check_goals(self._calibration, goals))
        self.set_torque(True)
