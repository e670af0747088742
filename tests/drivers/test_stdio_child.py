"""A simulator child killed while another thread calls it: the caller gets a DeviceError.

The arm-controller restart test's watcher read the UR simulator from a thread
while the test killed it; the call died of an AssertionError, the thread with
it, and the test then saw an arm that never moved (CI, 2026-11-26).
"""

from __future__ import annotations

import threading

from common.errors import DeviceError
from robot_side.arm.sim import URSimProcess


def _poll(sim: URSimProcess, answered: threading.Event, stop: threading.Event, errors: list):
    while not stop.is_set():
        try:
            sim.tcp_speed()
            answered.set()
        except DeviceError:
            pass
        except BaseException as e:  # what used to kill a watcher thread
            errors.append(e)
            return


def test_a_kill_during_calls_from_another_thread_is_a_device_error_to_the_caller():
    for _ in range(3):  # the kill lands at a different point of a call each time
        sim = URSimProcess().start()
        errors: list[BaseException] = []
        answered, stop = threading.Event(), threading.Event()
        threads = [
            threading.Thread(target=_poll, args=(sim, answered, stop, errors)) for _ in range(2)
        ]
        for t in threads:
            t.start()
        assert answered.wait(10), "the simulator never answered"
        sim.kill()
        stop.set()
        for t in threads:
            t.join(10)
        assert errors == [], errors
