"""ur-rtde's control thread is real-time only while a call waits on it (control_receiver.py).

Checked on a thread of this process made as the driver makes ur-rtde's (in the fair
scheduler, with the control thread's timer slack): its policy and slack read from ``/proc``.
"""

from __future__ import annotations

import os
import threading
from pathlib import Path

import pytest

from robot_side.arm.ur_rtde.connection import made_on_fair_thread
from robot_side.arm.ur_rtde.control_receiver import CONTROL_THREAD_SLACK_NS, ControlReceiver

pytestmark = pytest.mark.untimed  # no clock: scheduling read back


@pytest.fixture
def polling_thread():
    """The native id of a thread that sleeps in short turns, made fair with the slack."""
    quit_ = threading.Event()
    started: list[int] = []

    def make() -> threading.Thread:
        def run() -> None:
            started.append(threading.get_native_id())
            while not quit_.wait(0.0001):
                pass

        t = threading.Thread(target=run, daemon=True)
        t.start()
        return t

    thread = made_on_fair_thread(make, 0, CONTROL_THREAD_SLACK_NS)
    while not started:
        quit_.wait(0.001)
    yield started[0]
    quit_.set()
    thread.join()


def _slack_ns(tid: int) -> int:
    return int(Path(f"/proc/{tid}/timerslack_ns").read_text())


def test_the_control_thread_is_real_time_inside_a_call_and_fair_with_its_slack_after(
    polling_thread,
):
    tid = polling_thread
    assert os.sched_getscheduler(tid) == os.SCHED_OTHER
    assert _slack_ns(tid) == CONTROL_THREAD_SLACK_NS
    receiver = ControlReceiver(frozenset({tid}), 3)
    for _ in range(2):  # each call, not only the first
        with receiver.realtime():
            inside = (os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority)
        if receiver.refused is not None:  # no right to raise: fair throughout, and said once
            assert inside[0] == os.SCHED_OTHER
        else:
            assert inside == (os.SCHED_FIFO, 3)
        assert os.sched_getscheduler(tid) == os.SCHED_OTHER
        # the creator's slack again, not the system's default: its polls stay sparse
        assert _slack_ns(tid) == CONTROL_THREAD_SLACK_NS


def test_without_a_priority_or_a_thread_nothing_is_raised(polling_thread):
    for receiver in (ControlReceiver(frozenset({polling_thread}), 0), ControlReceiver()):
        with receiver.realtime():
            assert os.sched_getscheduler(polling_thread) == os.SCHED_OTHER
        assert receiver.refused is None


def test_a_thread_that_ended_is_skipped(polling_thread):
    ended: list[int] = []
    t = threading.Thread(target=lambda: ended.append(threading.get_native_id()))
    t.start()
    t.join()
    receiver = ControlReceiver(frozenset({ended[0], polling_thread}), 2)
    with receiver.realtime():
        pass
    assert receiver.refused is None
    assert os.sched_getscheduler(polling_thread) == os.SCHED_OTHER


def test_a_block_inside_another_leaves_the_thread_real_time_until_the_outer_one_ends(
    polling_thread,
):
    """A kick that finds a command on the wire ends its block first: the command still waits
    on a real-time thread."""
    receiver = ControlReceiver(frozenset({polling_thread}), 3)
    with receiver.realtime():
        with receiver.realtime():
            pass
        still = os.sched_getscheduler(polling_thread)
    assert os.sched_getscheduler(polling_thread) == os.SCHED_OTHER
    if receiver.refused is None:
        assert still == os.SCHED_FIFO
