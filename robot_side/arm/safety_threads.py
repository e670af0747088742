"""The arm's safety threads: the jog deadman, and the keep-alive a controller listens for.

The deadman thread stops a jog ``jog_timeout_s`` after it was issued unless
another came; the keep-alive thread (for a driver with a ``_keep_alive``)
tells the controller every deadman period that this process lives, so a
controller that watches for it (ur-rtde's watchdog) stops the arm when the
process cannot. Both run above the rest of the node, real-time where the
arm's own process is granted it.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Callable

from common.clocks.clock import now_s
from common.devices.lifecycle import at_niceness
from common.process.realtime import PeriodStats, Scheduling, raise_this_thread
from robot_side.arm.limits import deadman_period_s, jog_overdue_s

log = logging.getLogger(__name__)

#: The deadman's, the keep-alive's and a driver's control threads run above the rest of
#: the robot node (its unit's Nice=-10) where the process may raise them (the unit's
#: LimitNICE=-15), like ur-rtde's own ``rt_priority``. They sleep between short turns, so
#: they take little; what they need is the CPU when they wake. At the node's own priority
#: they queued behind ur-rtde's two receive threads (which poll every 100 us), the other
#: threads of the node and whatever else runs at -10: on a saturated 2-core machine the
#: keep-alive waited 168 ms for a CPU within 0.4 s (its schedstat) and the controller's
#: watchdog tripped. A driver used from a process at ordinary priority (a tool, a test, a
#: notebook) still stops its jogs and kicks its controller's watchdog. Their priority does
#: not help while a preempted thread of the node holds the interpreter lock they each need,
#: and the whole node at -15 starved the simulated hardware instead (docs/robustness.md).
SAFETY_THREAD_NICE = -15
#: ur-rtde's own threads (the receive loops that poll every 100 us) run at the robot unit's
#: Nice=-10 whichever thread connects (a reconnect may come from a -15 thread): they never
#: take the interpreter lock, and at -15 their polling would stand in front of the safety
#: threads. A driver in a process at lower priority leaves them at its own.
NATIVE_DRIVER_THREAD_NICE = -10


class SafetyThreads:
    """The deadman and keep-alive threads of an :class:`~robot_side.arm.base.Arm`.

    A mixin of the arm: the deadman stops through the arm's ``_lock``,
    ``_jog_until`` and ``_stop_locked``; the keep-alive calls the driver's
    ``_keep_alive``. The arm calls ``_init_safety_threads()`` once its
    ``limits`` are set.
    """

    def _init_safety_threads(self) -> None:
        self._deadman_stops = 0
        self._deadman_thread: threading.Thread | None = None
        self._keep_alive_thread: threading.Thread | None = None
        self._deadman_quit = threading.Event()
        self._deadman_woke = 0.0  # monotonic s: the deadman thread's latest wake
        self._deadman_stopping_since: float | None = None  # it waits for a stop since then
        #: SCHED_FIFO priority of the deadman and keep-alive threads (None: a niceness only);
        #: the arm's own process sets it (robot_side/arm/process)
        self.realtime_priority: int | None = None
        #: what the keep-alive thread got from the scheduler, once it runs
        self.keep_alive_scheduling: Scheduling | None = None
        #: the intervals between the keep-alive thread's wakes (nominal: the deadman period)
        self.keep_alive_periods = PeriodStats(deadman_period_s(self.limits))

    def keep_alive_summary(self) -> dict[str, float]:
        """The keep-alive's period (p50, p99, p999, max in ms, count) and whether it runs
        real-time (``realtime`` 1/0, ``level``: its priority or niceness); {} before it ran."""
        summary = self.keep_alive_periods.summary()
        if not summary:
            return {}
        got = self.keep_alive_scheduling
        summary.pop("nominal_ms", None)
        if got is not None:
            summary.update(realtime=float(got.realtime), level=float(got.level))
        return summary

    def keep_alive_telemetry(self) -> dict[str, float]:
        """How on time the keep-alive runs: its period's p99 and max (ms), and whether it runs
        real-time (1) or at a niceness (0); nothing for a driver without a keep-alive."""
        summary = self.keep_alive_periods.summary()
        if not summary:
            return {}
        got = self.keep_alive_scheduling
        return {
            "arm_keepalive_p99_ms": summary["p99_ms"],
            "arm_keepalive_max_ms": summary["max_ms"],
            "arm_keepalive_realtime": float(got is not None and got.realtime),
        }

    # -- deadman -----------------------------------------------------------

    def _start_deadman(self) -> None:
        """The deadman thread and, for a driver with a ``_keep_alive``, the thread that kicks."""
        self._deadman_quit.clear()
        self._jog_until = None
        self._deadman_woke = now_s()
        self.keep_alive_periods.clear()  # a new connection: a new series
        name = type(self).__name__
        t = threading.Thread(target=self._safety_thread(self._deadman_loop), name=f"{name}-deadman")
        t.daemon = True
        self._deadman_thread = t
        t.start()
        if type(self)._keep_alive is not SafetyThreads._keep_alive:
            k = threading.Thread(
                target=self._safety_thread(self._keep_alive_loop, note=True),
                name=f"{name}-keepalive",
            )
            k.daemon = True
            self._keep_alive_thread = k
            k.start()

    def _safety_thread(self, loop: Callable[[], None], note: bool = False) -> Callable[[], None]:
        """``loop`` at SCHED_FIFO ``realtime_priority`` where set and granted, else at the
        safety threads' niceness; ``note``: the keep-alive records what it got."""
        priority = self.realtime_priority
        if priority is None:

            def noted() -> None:
                if note:  # in the node (own_process = false): the niceness it got
                    tid = threading.get_native_id()
                    self.keep_alive_scheduling = Scheduling(
                        "nice", os.getpriority(os.PRIO_PROCESS, tid)
                    )
                loop()

            return at_niceness(SAFETY_THREAD_NICE, noted)

        def run() -> None:
            got = raise_this_thread(priority, SAFETY_THREAD_NICE)
            if note:
                self.keep_alive_scheduling = got
                log.info("%s keep-alive at %s", type(self).__name__, got.describe())
            loop()

        return run

    def _stop_deadman(self) -> None:
        self._deadman_quit.set()
        threads = (self._deadman_thread, self._keep_alive_thread)
        self._deadman_thread = self._keep_alive_thread = None
        for t in threads:
            if t is not None and t is not threading.current_thread():
                t.join(timeout=2.0)

    @property
    def deadman_responsive(self) -> bool:
        """The deadman thread could still stop a jog: it is making a stop that has not yet
        outlasted ``_deadman_stop_limit_s``; or no jog has outlived its deadline by more
        than ``jog_overdue_s`` and the thread woke within a jog's lifetime.

        Otherwise a keep-alive must let the controller's own watchdog stop the
        arm: an overdue jog that nobody stopped is the deadman starved (the CPU
        or the interpreter lock kept from it), and the box's reach
        (``jog_reach_s``) counts on the controller stopping it a watchdog
        window after the last kick.
        """
        now = now_s()
        since = self._deadman_stopping_since
        if since is not None:
            return now - since <= self._deadman_stop_limit_s()
        until = self._jog_until
        if until is not None and now - until > jog_overdue_s(self.limits):
            return False
        return now - self._deadman_woke <= self.limits.jog_timeout_s

    def _deadman_stop_limit_s(self) -> float:
        """The longest a stop (the lock's wait included) may take before the deadman counts as
        stuck; drivers whose calls have deadlines say theirs."""
        return 2.0

    @property
    def deadman_period_s(self) -> float:
        """How often the deadman thread wakes: its jog check and ``_keep_alive`` run this often."""
        return deadman_period_s(self.limits)

    def _keep_alive(self) -> None:
        """Tell the controller this process is alive; called every deadman period.

        Runs on a thread of its own, which lives and dies (or freezes) with
        this process, so a controller that watches for it stops the arm when
        the process cannot (ur-rtde's watchdog, ``URArm``). Not the deadman
        thread: that one makes the deadman's stops, and a stop may wait for
        the whole deceleration. It must never block. Nothing to do by default
        (and then no thread runs).
        """

    def _keep_alive_loop(self) -> None:
        """Every deadman period on absolute deadlines (a late turn does not push the next
        back); each wake is noted in ``keep_alive_periods``."""
        period = self.deadman_period_s
        due = now_s() + period
        while not self._sleep_unless_quit(due - now_s()):
            now = now_s()
            self.keep_alive_periods.woke(now)
            due += period
            if due < now:  # more than a period late: start again from now, no burst of turns
                due = now + period
            try:
                self._keep_alive()
            except Exception:  # the next period tries again
                log.exception("%s: keep-alive failed", type(self).__name__)

    def _watch_spins(self) -> None:
        """Called on every deadman turn: a driver whose real-time calls may busy-wait
        bounds them here (``URArm``: ``SpinGuard``). Nothing by default."""

    def _sleep_unless_quit(self, seconds: float) -> bool:
        """Sleep ``seconds`` (none if not positive); True once the threads are to end.

        A plain sleep, not ``Event.wait``: on a VM the event's condition took 15 to 30 us
        more of each turn, and both threads turn 50 times a second. An end is noticed
        within a period (``_stop_deadman`` waits for it).
        """
        if seconds > 0:
            time.sleep(seconds)
        return self._deadman_quit.is_set()

    def _deadman_loop(self) -> None:
        period = self.deadman_period_s
        while not self._sleep_unless_quit(period):
            self._deadman_woke = now_s()
            self._watch_spins()
            until = self._jog_until
            if until is None or now_s() < until:
                continue
            self._deadman_stopping_since = now_s()
            try:
                self._deadman_stop()
            finally:
                self._deadman_stopping_since = None

    def _deadman_stop(self) -> None:
        with self._lock:
            if self._jog_until is None or now_s() < self._jog_until:
                return  # a jog or stop arrived meanwhile
            log.warning("no jog for %.2f s: stopping the arm (deadman)", self.limits.jog_timeout_s)
            self._deadman_stops += 1
            try:
                self._stop_locked()
            except Exception:  # the thread must survive to try again
                log.exception("deadman stop failed")
                self._jog_until = now_s() + self.limits.jog_timeout_s
