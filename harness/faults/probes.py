"""Observers outside every process that can fail: the arm, the gripper and the palm.

Each probe is a thread that samples one device's simulator over what a
bystander could read (the UR's RTDE output, the URCap socket, the servo
bus's front panel) and keeps a time series on the monotonic clock, which
every process on the machine shares. A probe survives its device dying
and coming back: it reconnects and records the gap as missing samples.
"""

from __future__ import annotations

import abc
import bisect
import contextlib
import json
import logging
import math
import socket
import threading
import time
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger(__name__)


@dataclass(frozen=True, order=True)
class Sample:
    t_s: float  # monotonic, this machine
    value: float  # what the probe measures (m/s, finger counts, ...)


class _Probe(abc.ABC):
    period_s = 0.01

    def __init__(self, name: str) -> None:
        self.samples: list[Sample] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name=f"probe-{name}", daemon=True)

    def start(self) -> _Probe:
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)

    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                value = self.read()
            except Exception as e:
                log.debug("%s: %r", type(self).__name__, e)
                self.reset()
                self._stop.wait(0.1)
                continue
            if value is not None:
                self.samples.append(Sample(time.monotonic(), value))
            self._stop.wait(self.period_s)

    @abc.abstractmethod
    def read(self) -> float | None:
        """One reading from outside the failing process; None: nothing to read now."""

    def reset(self) -> None:  # noqa: B027 (a probe without a connection has nothing to drop)
        """Drop the connection after an error; the next read opens a new one."""

    def between(self, t0: float, t1: float = math.inf) -> list[Sample]:
        return [s for s in list(self.samples) if t0 <= s.t_s < t1]


class ArmProbe(_Probe):
    """The TCP's linear speed (m/s), read from the UR simulator with ur-rtde's receive interface.

    A sample is kept only when the controller's timestamp advanced, so a
    frozen or dead controller shows as a gap, never as a still arm.
    """

    period_s = 0.008

    def __init__(self, host: str) -> None:
        super().__init__("arm")
        self.host = host
        self._rtde = None
        self._last_stamp: float | None = None

    def read(self) -> float | None:
        if self._rtde is None:
            import rtde_receive

            self._rtde = rtde_receive.RTDEReceiveInterface(self.host, 125.0)
        if not self._rtde.isConnected():
            raise ConnectionError("RTDE receive interface disconnected")
        stamp = self._rtde.getTimestamp()
        if stamp == self._last_stamp:
            return None
        self._last_stamp = stamp
        v = self._rtde.getActualTCPSpeed()
        return math.sqrt(v[0] ** 2 + v[1] ** 2 + v[2] ** 2)

    def reset(self) -> None:
        if self._rtde is not None:
            with contextlib.suppress(Exception):
                self._rtde.disconnect()
        self._rtde = None
        self._last_stamp = None

    def close(self) -> None:
        super().close()
        self.reset()


class GripperProbe(_Probe):
    """The fingers' position (0 open .. 255 closed) and the object flag, from the URCap socket."""

    period_s = 0.05

    def __init__(self, host: str, port: int) -> None:
        super().__init__("gripper")
        self.address = (host, port)
        self._sock: socket.socket | None = None
        self._file = None
        #: (t_s, OBJ) for every position sample: 2 = stopped on an object while closing
        self.objects: list[Sample] = []

    def _get(self, register: str) -> int:
        assert self._sock is not None and self._file is not None
        self._sock.sendall(f"GET {register}\n".encode())
        line = self._file.readline()
        if not line:
            raise ConnectionError("gripper closed the connection")
        name, _, value = line.decode().strip().partition(" ")
        if name != register:
            raise ConnectionError(f"gripper answered {line!r} to GET {register}")
        return int(value)

    def read(self) -> float | None:
        if self._sock is None:
            self._sock = socket.create_connection(self.address, timeout=0.5)
            self._file = self._sock.makefile("rb")
        position = self._get("POS")
        self.objects.append(Sample(time.monotonic(), self._get("OBJ")))
        return float(position)

    def reset(self) -> None:
        if self._sock is not None:
            with contextlib.suppress(OSError):
                self._sock.close()
        self._sock = self._file = None


class PalmProbe(_Probe):
    """The palm from the servo bus's front panel (``deepxpalm sim servos --status-file``).

    The value is how far the linkages are from lifted off: the largest
    difference, in counts, between a goal and its retract goal (0: off the palm).
    """

    period_s = 0.01

    def __init__(self, status_file: Path, retract_goals: list[int]) -> None:
        super().__init__("palm")
        self.status_file = status_file
        self.retract = retract_goals
        self._last_t_ns: int | None = None
        self._logged_ns: int | None = None  # the newest goal-log entry taken
        self._log_goals: list[int] | None = None
        #: (t_s, servo id, present counts) of each torque off, at the bus's time: where a
        #: servo was let go (a linkage let go mid-way stays there)
        self.releases: list[tuple[float, int, int]] = []
        #: (t_s, servo id, goal) of each goal write, at the bus's time
        self.goal_writes: list[tuple[float, int, int]] = []

    def first_write_after(self, t_s: float) -> float:
        """When the bus took its first goal write at or after ``t_s`` (inf: none yet)."""
        return min((t for t, _, _ in self.goal_writes if t >= t_s), default=math.inf)

    def read(self) -> float | None:
        """None: the panel's sample is placed at its own time (below), not at this read's."""
        panel = json.loads(self.status_file.read_text())
        if panel["t_ns"] == self._last_t_ns:
            return None  # the bus simulator is not running: no news
        self._last_t_ns = panel["t_ns"]
        goals = [panel["goals"][str(i + 1)] for i in range(len(self.retract))]
        # the torque offs before the goal writes: a reader who sees a write (a test waiting
        # for the lift's first one) then sees every torque off the same panel held
        taken = self.releases[-1][0] if self.releases else float("-inf")
        self.releases += [
            (t / 1e9, i, p) for t, i, p in panel.get("release_log", []) if t / 1e9 > taken
        ]
        self._replay_goal_log(panel.get("goal_log", []), goals)
        # at the panel's own time, as the log's writes are: read late (this thread starved), a
        # panel stamped when read would stand after writes it does not hold yet, and show the
        # palm pressed again just after a lift the log placed earlier
        bisect.insort(self.samples, Sample(panel["t_ns"] / 1e9, self._distance(goals)))
        return None

    def _distance(self, goals: list[int]) -> float:
        return float(max(abs(g - r) for g, r in zip(goals, self.retract, strict=True)))

    def _replay_goal_log(self, entries: list[list[int]], now_goals: list[int]) -> None:
        """Every goal write since the last panel, as a sample at the bus's own time: a lift
        shorter than the panel's period, or one a stalled probe slept through, still shows.

        The writes are replayed onto the previous panel's goals. A first panel (a probe that
        started late, after a node's first writes) replays its log from nothing known: a
        sample from the first write that leaves every servo's goal known (one sync write).
        """
        if not entries:
            return
        new = [e for e in entries if self._logged_ns is None or e[0] > self._logged_ns]
        self._logged_ns = max(e[0] for e in entries)
        goals: list[int | None] = (
            list(self._log_goals) if self._log_goals is not None else [None] * len(now_goals)
        )
        for t_ns, sid, goal in sorted(new):
            self.goal_writes.append((t_ns / 1e9, sid, goal))
            if 1 <= sid <= len(goals):
                goals[sid - 1] = goal
                if all(g is not None for g in goals):
                    bisect.insort(self.samples, Sample(t_ns / 1e9, self._distance(goals)))
        self._log_goals = list(now_goals)  # the panel is the truth between logs
