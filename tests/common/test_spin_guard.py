"""A real-time call that busy-waits goes fair after its limit, and real-time again after it.

A thread of this process raised to SCHED_FIFO spins, as ur-rtde's ``sendCommand`` does
for a "ready" that is not coming; another thread checks as the arm's deadman does. The
policy is read back from the kernel, inside and after the call.
"""

from __future__ import annotations

import contextlib
import os
import threading
import time

from common.process.spin_guard import SpinGuard

LIMIT_S = 0.02


def _spin_on_fifo(guard: SpinGuard, seen: dict) -> None:
    """On a thread: SCHED_FIFO 1 if granted, then one watched call that spins until it is
    no longer real-time (or 2 s: the check failed)."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    except OSError as e:
        seen["refused"] = e.strerror
    start = time.monotonic()
    with guard.watched("a spinning call"):
        while os.sched_getscheduler(0) != os.SCHED_OTHER and time.monotonic() - start < 2.0:
            pass
        seen["inside"] = os.sched_getscheduler(0)
        seen["spun_s"] = time.monotonic() - start
    seen["after"] = os.sched_getscheduler(0)


def test_a_spinning_real_time_call_goes_fair_after_the_limit_and_comes_back():
    guard = SpinGuard(LIMIT_S)
    seen: dict = {}
    spinner = threading.Thread(target=_spin_on_fifo, args=(guard, seen), daemon=True)
    spinner.start()
    while spinner.is_alive():
        guard.check()
        time.sleep(0.002)
    spinner.join()
    if "refused" in seen:  # no right to raise: nothing real-time to guard, nothing moved
        assert guard.demotions == 0 and seen["after"] == os.SCHED_OTHER
        return
    assert guard.demotions == 1
    assert seen["inside"] == os.SCHED_OTHER
    assert LIMIT_S <= seen["spun_s"] < 2.0  # not before its limit; the 2 s is the check failing
    assert seen["after"] == os.SCHED_FIFO  # its priority back once the call returned


def test_a_call_that_returns_in_time_keeps_its_priority_and_a_fair_thread_is_left_alone():
    guard = SpinGuard(LIMIT_S)
    seen: dict = {}

    def quick() -> None:
        with contextlib.suppress(OSError):
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
        with guard.watched("a quick call"):
            seen["inside"] = os.sched_getscheduler(0)
        seen["after"] = os.sched_getscheduler(0)

    t = threading.Thread(target=quick)
    t.start()
    t.join()
    assert not guard.check()  # nothing watched any more
    assert seen["inside"] == seen["after"]
    # a fair thread's call is not watched at all: a check never touches it, however long
    with guard.watched("a fair call"):
        time.sleep(LIMIT_S * 2)
        assert not guard.check()
    assert guard.demotions == 0
