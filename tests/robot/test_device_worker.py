"""Device calls on their own thread: posting never waits on the device, and the newest wins."""

from __future__ import annotations

import itertools
import threading
import time

from robot_side.devices.device_worker import DeviceRequest, DeviceWorker
from robot_side.devices.recovery import DeviceRecovery


class SlowDevice:
    is_connected = True

    def __init__(self) -> None:
        self.calls: list[str] = []
        self.release = threading.Event()
        self.started = threading.Event()

    def act(self, name: str) -> str:
        if name == "slow":
            self.started.set()
            self.release.wait(5)
        self.calls.append(name)
        return name


def _worker(device: SlowDevice, **kw) -> DeviceWorker:
    return DeviceWorker("test", DeviceRecovery(device, "test", threading.Event()), **kw)


def _wait(predicate, timeout_s: float = 3.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.005)
    return predicate()


def test_posting_returns_while_the_device_is_still_busy_and_only_the_newest_waiting_runs():
    device = SlowDevice()
    worker = _worker(device)
    try:
        worker.post(DeviceRequest("slow", device.act, ("slow",)))
        assert device.started.wait(3)
        for name in ("a", "b", "c"):
            worker.post(DeviceRequest(name, device.act, (name,)))
        assert device.calls == []  # every post returned before the slow call ended
        device.release.set()
        assert _wait(lambda: worker.idle)
        assert device.calls == ["slow", "c"]
        assert worker.counters["superseded"] == 2
    finally:
        device.release.set()
        worker.close()


def test_close_runs_the_last_request_after_the_running_one():
    device = SlowDevice()
    worker = _worker(device)
    worker.post(DeviceRequest("slow", device.act, ("slow",)))
    assert device.started.wait(3)
    worker.post(DeviceRequest("jog", device.act, ("jog",)))
    threading.Timer(0.1, device.release.set).start()
    worker.close(DeviceRequest("stop", device.act, ("stop",)))
    assert device.calls == ["slow", "stop"]  # the pending jog never ran


def test_a_failing_call_is_reported_and_the_worker_goes_on():
    device = SlowDevice()
    outcomes: list[object] = []

    def boom() -> None:
        raise ValueError("refused")

    worker = _worker(device)
    try:
        worker.post(DeviceRequest("x", boom, on_done=lambda r, res, err: outcomes.append(err)))
        assert _wait(lambda: outcomes)
        assert isinstance(outcomes[0], ValueError)
        worker.post(DeviceRequest("ok", device.act, ("ok",)))
        assert _wait(lambda: device.calls == ["ok"])
    finally:
        worker.close()


def test_an_idle_worker_polls_the_device_at_its_interval():
    device = SlowDevice()
    polls: list[float] = []
    worker = _worker(device, idle_poll=lambda: polls.append(time.monotonic()), idle_poll_s=0.02)
    deadline = time.monotonic() + 10.0  # a starved worker polls late, never early
    try:
        while len(polls) < 6 and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        worker.close()
    assert len(polls) >= 6, f"{len(polls)} polls in 10 s at a 20 ms interval"
    # the next poll is due an interval after the last one began (its own call's time apart)
    gaps = [b - a for a, b in itertools.pairwise(polls)]
    assert min(gaps) >= 0.01, f"polled {min(gaps) * 1e3:.1f} ms apart at a 20 ms interval"


def test_a_paced_request_waits_its_gap_the_newest_goes_and_a_stop_never_waits():
    device = SlowDevice()
    stamps: list[tuple[str, float]] = []

    def act(name: str) -> str:
        stamps.append((name, time.monotonic()))
        return device.act(name)

    gap = 0.05
    worker = _worker(device, paced={"jog": gap})
    try:
        t0 = time.monotonic()
        for i in range(200):  # a flood of jogs over about 0.2 s
            worker.post(DeviceRequest("jog", act, (f"jog{i}",)))
            time.sleep(0.001)
        assert _wait(lambda: worker.idle)
        jogs = [t for name, t in stamps if name.startswith("jog")]
        span = jogs[-1] - t0
        assert len(jogs) <= span / gap + 2, (len(jogs), span)  # not one call per post
        assert min(b - a for a, b in itertools.pairwise(jogs)) >= gap * 0.95
        assert device.calls[-1] == "jog199"  # the newest still went
    finally:
        worker.close()
    # a stop posted while a jog waits for its pace (1 s here) runs at once, and that jog never
    worker = _worker(device, paced={"jog": 1.0})
    try:
        worker.post(DeviceRequest("jog", act, ("first-jog",)))
        assert _wait(lambda: worker.idle)
        worker.post(DeviceRequest("jog", act, ("paced-jog",)))
        t_stop = time.monotonic()
        worker.post(DeviceRequest("stop", act, ("stop",)))
        assert _wait(lambda: worker.idle)
        assert stamps[-1][0] == "stop" and stamps[-1][1] - t_stop < 0.5
        assert "paced-jog" not in device.calls
    finally:
        worker.close()
