"""Device calls off the frame loop: one thread per device, and the newest request wins.

The frame loop must never wait on a device. A UR stop returns only when the
arm has decelerated (hundreds of milliseconds), a Robotiq call costs a
Modbus round trip, and a dead controller costs a timeout. So the loop posts
a request and goes on; the device's worker thread makes the call. A request
that has not started when a newer one arrives is replaced, not queued: the
newer one is what the operator wants now, and a queue would turn a burst of
commands into seconds of lag.

Some requests are paced: a jog renews the same motion, and a flood of them
(one per incoming command, as fast as the device answers) only costs the
robot PC its CPU. A paced request waits until its gap since the last of its
kind has passed; a newer request replaces it meanwhile, and any other kind
(a stop) runs at once.

Between requests a worker may poll the device (the gripper's grip level for
the stimuli), so the loop reads a cached value instead of the device.
"""

from __future__ import annotations

import logging
import threading
from collections import Counter
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from common.clocks.clock import now_s
from robot_side.devices.recovery import DeviceRecovery

log = logging.getLogger(__name__)


@dataclass(slots=True)
class DeviceRequest:
    """One call to make on a device, and whom to tell how it went."""

    action: str  # what it is, for logs and records ("arm_jog", "arm_stop", ...)
    call: Callable[..., Any]
    args: tuple[Any, ...] = ()
    #: called on the worker thread with (request, result, error); error None when it worked
    on_done: Callable[[DeviceRequest, Any, BaseException | None], None] | None = None


class DeviceWorker:
    """Runs one device's calls on its own thread; a pending request is replaced by a newer one."""

    def __init__(
        self,
        name: str,
        recovery: DeviceRecovery,
        *,
        idle_poll: Callable[[], None] | None = None,
        idle_poll_s: float = 0.05,
        paced: Mapping[str, float] | None = None,
    ) -> None:
        self.name = name
        #: action -> the least time between the starts of two calls of it (s)
        self._paced = dict(paced or {})
        self._last_start: dict[str, float] = {}
        self.recovery = recovery
        self._idle_poll = idle_poll
        self._idle_poll_s = idle_poll_s
        self._cond = threading.Condition()
        self._pending: DeviceRequest | None = None
        self._closing = False
        self._busy = False
        #: requests posted / replaced before they started / done / failed (this thread's own)
        self.counters: Counter[str] = Counter()
        self._thread = threading.Thread(target=self._run, name=f"{name}-worker", daemon=True)
        self._thread.start()

    def post(self, request: DeviceRequest) -> None:
        """Hand a request to the worker; never blocks on the device."""
        with self._cond:
            if self._closing:
                return
            if self._pending is not None:
                self.counters["superseded"] += 1
            self._pending = request
            self.counters["posted"] += 1
            self._cond.notify()

    @property
    def idle(self) -> bool:
        """Nothing pending and nothing running (tests and shutdown wait for this)."""
        with self._cond:
            return self._pending is None and not self._busy

    def close(self, last: DeviceRequest | None = None, timeout_s: float = 5.0) -> None:
        """Run ``last`` (a stop) after whatever is running, then end the thread."""
        with self._cond:
            if last is not None:
                if self._pending is not None:
                    self.counters["superseded"] += 1
                self._pending = last
            self._closing = True
            self._cond.notify()
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            log.error("%s worker still busy after %.1f s at shutdown", self.name, timeout_s)

    def _run(self) -> None:
        next_poll = now_s()
        while True:
            with self._cond:
                if self._pending is None and not self._closing:
                    wait = None if self._idle_poll is None else max(0.0, next_poll - now_s())
                    self._cond.wait(wait)
                early = self._too_early(self._pending)
                if early > 0 and not self._closing:
                    self._cond.wait(early)  # a newer request may replace it meanwhile
                    continue
                request, self._pending = self._pending, None
                if request is None and self._closing:
                    return
                self._busy = True
            try:
                if request is not None:
                    self._execute(request)
                if self._idle_poll is not None and now_s() >= next_poll:
                    next_poll = now_s() + self._idle_poll_s
                    if self.recovery.available:
                        self._poll()
            finally:
                with self._cond:
                    self._busy = False

    def _too_early(self, request: DeviceRequest | None) -> float:
        """How long ``request`` must still wait for its pace (0: it may run now)."""
        if request is None or request.action not in self._paced:
            return 0.0
        last = self._last_start.get(request.action)
        return 0.0 if last is None else last + self._paced[request.action] - now_s()

    def _execute(self, request: DeviceRequest) -> None:
        if request.action in self._paced:
            self._last_start[request.action] = now_s()
        result: Any = None
        error: BaseException | None = None
        try:
            result = self.recovery.call(request.call, *request.args)
            self.counters["done"] += 1
        except Exception as e:  # reported to on_done; the worker must survive any driver
            error = e
            self.counters["failed"] += 1
        if request.on_done is not None:
            try:
                request.on_done(request, result, error)
            except Exception:
                log.exception("%s: reporting %s failed", self.name, request.action)

    def _poll(self) -> None:
        try:
            self.recovery.call(self._idle_poll)
        except Exception as e:  # a poll failing is counted; the next one may work
            self.counters["poll_errors"] += 1
            log.debug("%s: poll failed: %s", self.name, e)
