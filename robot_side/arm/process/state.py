"""The arm process's newest state, shared with the robot node through memory, never waited on.

The arm process writes it every ``WRITE_EVERY_S``; the robot node reads it
for each heartbeat and for its reconnect decisions. A sequence counter
around every write (a seqlock: odd while writing) lets the reader take a
consistent copy without a lock either side could be held on: a reader that
meets a write in progress tries again, at most a few times, and otherwise
keeps the copy it had.
"""

from __future__ import annotations

import mmap
import os
import struct
import tempfile
from dataclasses import dataclass
from pathlib import Path

from common.errors import DeviceError, DeviceNotConnectedError
from robot_side.arm.base import TELEMETRY_POSE_KEYS

SPEED_KEYS = ("arm_speed_m_s", "arm_angular_speed_rad_s")
#: what of the driver's telemetry the state carries beside the pose and speed (the envelope is
#: the node's own: its limits are the arm process's)
TELEMETRY_STATE_KEYS = (
    "arm_jogging",
    "arm_deadman_stops",
    "arm_safety_mode",
    "arm_program_running",
)
#: the state is written this often: the rate of the robot's heartbeat, for which the node reads
#: it (written every keep-alive period, 20 ms, the writer's thread took 1.8 % of a core on a VM;
#: at this rate 0.9 %)
WRITE_EVERY_S = 0.05

#: the values after the sequence counter, in order
FIELDS = (
    "t_write_s",
    "connected",
    "needs_reconnect",
    "live",
    *TELEMETRY_POSE_KEYS,
    *SPEED_KEYS,
    "keepalive_count",
    "keepalive_p50_ms",
    "keepalive_p99_ms",
    "keepalive_p999_ms",
    "keepalive_max_ms",
    "keepalive_realtime",
    "keepalive_level",
    # the driver's telemetry (``Arm.telemetry``)
    "telemetry_ok",
    *TELEMETRY_STATE_KEYS,
)
_SEQ = struct.Struct("<Q")
_VALUES = struct.Struct(f"<{len(FIELDS)}d")
SIZE = _SEQ.size + _VALUES.size
_READ_TRIES = 4


def telemetry_of(state: dict[str, float] | None, stale_s: float) -> dict[str, float]:
    """What of the arm's telemetry only the driver in the arm process took (no envelope, no
    pose: ``live_of``), from its newest state; DeviceError when there is none to give, and
    why."""
    if state is None:
        raise DeviceNotConnectedError(
            f"arm process: its state is older than {stale_s * 1000:.0f} ms (it stopped its turns)"
        )
    if not state.get("telemetry_ok"):
        raise DeviceError("arm process: its driver could not read the arm (its log says why)")
    return {k: state[k] for k in TELEMETRY_STATE_KEYS}


def live_of(state: dict[str, float] | None) -> dict[str, float]:
    """The pose and speed the driver streamed, with the keep-alive's timing; nothing while the
    stream is not live (or there is no state)."""
    if state is None or not state.get("live"):
        return {}
    return {k: state[k] for k in (*TELEMETRY_POSE_KEYS, *SPEED_KEYS)} | keep_alive_of(state)


def keep_alive_of(state: dict[str, float] | None) -> dict[str, float]:
    """The keep-alive's timing as the heartbeat names it; nothing before its first period."""
    if state is None or not state.get("keepalive_count"):
        return {}
    return {
        "arm_keepalive_p99_ms": state["keepalive_p99_ms"],
        "arm_keepalive_max_ms": state["keepalive_max_ms"],
        "arm_keepalive_realtime": state["keepalive_realtime"],
    }


def new_state_file() -> Path:
    """A file for one arm process's state, in shared memory where the system has it."""
    where = "/dev/shm" if os.path.isdir("/dev/shm") else None
    fd, path = tempfile.mkstemp(prefix="deepxpalm-arm-", suffix=".state", dir=where)
    try:
        os.write(fd, bytes(SIZE))
    finally:
        os.close(fd)
    return Path(path)


@dataclass
class StateView:
    """One side's mapping of the state file."""

    path: Path

    def __post_init__(self) -> None:
        with open(self.path, "r+b") as f:
            self._map = mmap.mmap(f.fileno(), SIZE)
        self._seq = 0
        self._last: dict[str, float] = {}

    # ------------------------------------------------------------ the arm process
    def write(self, values: dict[str, float]) -> None:
        self._seq += 1
        _SEQ.pack_into(self._map, 0, self._seq * 2 - 1)  # odd: a write in progress
        _VALUES.pack_into(self._map, _SEQ.size, *(float(values.get(k, 0.0)) for k in FIELDS))
        _SEQ.pack_into(self._map, 0, self._seq * 2)

    # ------------------------------------------------------------ the robot node
    def read(self) -> dict[str, float]:
        """The newest complete state ({} before the first write, and once closed: the node's
        recovery closes the view on its own thread while the loop may be reading it)."""
        try:
            for _ in range(_READ_TRIES):
                (before,) = _SEQ.unpack_from(self._map, 0)
                if before == 0:
                    return {}
                if before % 2:
                    continue
                values = _VALUES.unpack_from(self._map, _SEQ.size)
                (after,) = _SEQ.unpack_from(self._map, 0)
                if after == before:
                    self._last = dict(zip(FIELDS, values, strict=True))
                    break
        except ValueError:  # "mmap closed or invalid"
            return {}
        return self._last

    def close(self) -> None:
        self._map.close()
