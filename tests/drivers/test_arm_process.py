"""The arm's real-time duties in a process of their own, checked at the simulated controller.

The robot node's driver runs in an arm process (``robot_side.arm.process``):
its keep-alive on time and real-time where granted, the node's death a stop
at once (not the controller's watchdog a window later), the arm process's
death a stop by the controller's watchdog, and the node reconnecting after it.
What moved is read from the UR simulator, not from the driver.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
from tests_support import fifo_granted

from common.devices.lifecycle import build_device
from common.errors import DeviceError
from common.process.realtime import PeriodStats
from harness.processes import thread_policies
from robot_side.arm import KINDS
from robot_side.arm.process import ArmProcess, dashboard_stop
from robot_side.arm.sim import URSimConfig, URSimProcess
from robot_side.arm.ur_rtde import URArmConfig

pytestmark = pytest.mark.slow

JOG = [0.02, 0.0, 0.0, 0.0, 0.0, 0.0]
WINDOW_S = URArmConfig().watchdog_window_s
#: a stop from the jog's speed at the stop deceleration, and the simulator's tick
DECEL_S = 0.02 / 2.0 + 0.01


def _at_rest(sim: URSimProcess) -> bool:
    return float(np.linalg.norm(sim.tcp_speed()[:3])) < 1e-4


def _wait(cond, timeout_s: float) -> float | None:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        if cond():
            return time.monotonic() - t0
        time.sleep(0.002)
    return None


def _unnamed_realtime_threads(pid: int) -> list[str]:
    """The arm process's threads at a real-time policy that are neither its main thread nor
    one it named for its duties (a library's pool thread, which may spin while it waits)."""
    return [
        key
        for key, policy in thread_policies(pid).items()
        if policy != os.SCHED_OTHER and key.startswith("python#")
    ]


def test_a_period_histogram_gives_the_percentiles_of_its_wakes():
    stats = PeriodStats(0.02)
    t = 0.0
    for i in range(2000):
        t += 0.02 + (0.1 if i == 1000 else 0.0)
        stats.woke(t)
    s = stats.summary()
    assert s["count"] == 1999 and s["p50_ms"] == pytest.approx(20.0, abs=0.06)
    assert s["max_ms"] == pytest.approx(120.0) and s["p999_ms"] <= 120.0
    stats.clear()
    assert stats.summary() == {}


def test_the_keep_alive_runs_in_the_arm_process_on_time_and_says_how():
    arm = build_device(KINDS, {"kind": "simulated"}, "arm")
    assert isinstance(arm, ArmProcess)
    arm.connect()
    try:
        assert arm.pid is not None and arm.ready_info == arm.pid
        time.sleep(1.5)
        summary = arm.keep_alive_summary()
        # what the scheduler gave it, as the doctor would see it on this machine
        assert summary["realtime"] == float(fifo_granted())
        assert summary["count"] >= 40
        assert summary["p50_ms"] == pytest.approx(20.0, abs=1.0)
        # from shared memory: the pose, and the keep-alive's timing. Not live for a moment when
        # the receive thread (fair, by design) was starved past the stream's 100 ms staleness
        # on a busy machine: the state says so rather than pass off an old pose
        wanted = {"arm_x", "arm_speed_m_s", "arm_keepalive_p99_ms"}
        reads: list[dict] = []
        _wait(lambda: reads.append(arm.live_readings()) or wanted <= set(reads[-1]), 1.0)
        assert wanted <= set(reads[-1]), f"not live within 1 s: {reads[-1]}"
        # no thread it did not start for its duties runs real-time (numpy's BLAS pool thread
        # did: it spins while it waits for work, and held a core at every start)
        assert _unnamed_realtime_threads(arm.pid) == []
    finally:
        arm.disconnect()
    assert arm.pid is None


NODE = textwrap.dedent(
    """
    import sys, time
    from common.devices.lifecycle import build_device
    from robot_side.arm import KINDS
    arm = build_device(KINDS, {"kind": "ur_rtde", "host": sys.argv[1]}, "arm")
    arm.connect()
    print(arm.pid, flush=True)
    while True:
        arm.jog([0.02, 0, 0, 0, 0, 0])
        time.sleep(0.05)
    """
)


def test_a_killed_robot_node_has_its_arm_stopped_by_the_arm_process_at_once():
    with URSimProcess(URSimConfig()) as sim:
        node = subprocess.Popen(
            [sys.executable, "-c", NODE, sim.host], stdout=subprocess.PIPE, text=True
        )
        try:
            arm_pid = int(node.stdout.readline())
            assert _wait(lambda: not _at_rest(sim), 10.0) is not None, "the jog never started"
            time.sleep(0.3)
            trips = sim.stats()["watchdog_trips"]
            node.send_signal(signal.SIGKILL)
            stopped = _wait(lambda: _at_rest(sim), 2.0)
        finally:
            node.kill()
            node.wait()
        # the arm process saw its node go (its stdin closed) and stopped the arm itself: well
        # inside the controller's window, and the controller's watchdog never had to trip
        assert stopped is not None and stopped < WINDOW_S, stopped
        assert sim.stats()["watchdog_trips"] == trips
        gone = _wait(lambda: subprocess.run(["kill", "-0", str(arm_pid)]).returncode != 0, 5.0)
        assert gone is not None, "the arm process outlived its node"


def _jog_until_moving(arm, sim, timeout_s: float) -> float | None:
    """Seconds until the controller's TCP moves, jogging as a held key does meanwhile (renewed
    every 50 ms, inside the 0.25 s deadman). A single jog that reached a busy arm process
    late was ended by the deadman before this poll saw the arm move (a quiet CI run's
    deployment lane)."""
    t0 = time.monotonic()
    next_jog = t0
    while time.monotonic() - t0 < timeout_s:
        if time.monotonic() >= next_jog:
            arm.jog(JOG)
            next_jog += 0.05
        if not _at_rest(sim):
            return time.monotonic() - t0
        time.sleep(0.002)
    return None


@contextlib.contextmanager
def _jogging_simulated_arm():
    """(the node's arm, its simulated controller), the arm jogging; disconnected after."""
    arm = build_device(KINDS, {"kind": "simulated"}, "arm")
    arm.connect()
    try:
        sim = arm.local.sim
        assert _jog_until_moving(arm, sim, 2.0) is not None
        yield arm, sim
    finally:
        arm.disconnect()


def test_the_node_presses_stop_on_the_dashboard_once_when_it_notices_its_arm_process_died(
    monkeypatch,
):
    import robot_side.arm.process as arm_process

    pressed: list[tuple[str, str]] = []

    def press_stop(host: str, why: str):
        pressed.append((host, why))
        return dashboard_stop.press_stop(host, why)

    monkeypatch.setattr(arm_process, "press_stop", press_stop)
    with _jogging_simulated_arm() as (arm, sim):
        arm.kill()
        for _ in range(3):  # the jogs that keep coming, and the recovery's check
            with pytest.raises(DeviceError):
                arm.jog(JOG)
        assert arm.needs_reconnect
        assert pressed == [(sim.host, "the arm process ended")]
        assert _wait(lambda: _at_rest(sim), 2.0) is not None


def test_stop_on_the_dashboard_ends_the_program_and_stops_the_arm():
    with _jogging_simulated_arm() as (arm, sim):
        dashboard_stop.press_stop(sim.host, "a test").join(5.0)
        assert _wait(lambda: _at_rest(sim), 1.0) is not None
        assert sim.stats()["program_ends"][-1][1] == "stop on the dashboard"
        # the node's telemetry poll, from the shared state, says the arm cannot be read now
        assert _wait(lambda: _telemetry_error(arm) is not None, 1.0) is not None
        assert "its driver could not read the arm" in _telemetry_error(arm)
        assert _wait(lambda: arm.needs_reconnect, 0.5) is not None  # in the same write or the next


def _telemetry_error(arm: ArmProcess) -> str | None:
    try:
        arm.telemetry()
    except DeviceError as e:
        return str(e)
    return None


def test_the_nodes_telemetry_comes_from_the_arm_process_state_not_a_call():
    """The node's telemetry poll reads what the driver in the arm process took (the pose, the
    jog, the program and safety state, the envelope), through shared memory: the pipe carries
    no call for it."""
    with _jogging_simulated_arm() as (arm, sim):
        calls = []
        call = arm._call
        arm._call = lambda *a, **k: calls.append(a[0]) or call(*a, **k)

        def jogging() -> bool:  # taken at the heartbeat's rate: seen within 50 ms of the jog
            arm.jog(JOG)
            return arm.telemetry()["arm_jogging"] == 1.0

        assert _wait(jogging, 1.0) is not None
        tel = arm.telemetry()
        assert tel["arm_program_running"] == 1.0
        assert tel["arm_safety_mode"] == 1.0  # normal
        assert tel["arm_max_linear_m_s"] == arm.limits.max_linear_speed_m_s
        arm.stop()
        assert _wait(lambda: _at_rest(sim), 1.0) is not None

        def at_rest() -> bool:  # in the next telemetry the arm process takes
            tel = arm.telemetry()
            return tel["arm_jogging"] == 0.0 and tel.get("arm_speed_m_s", 1.0) < 1e-3

        assert _wait(at_rest, 1.0) is not None, arm.telemetry()
        tel = arm.telemetry()
        pose = sim.tcp_pose()
        got = [tel[k] for k in ("arm_x", "arm_y", "arm_z")]
        assert np.allclose(got, pose[:3], atol=1e-4), (got, pose)
        # the keep-alive's timing, summed up once a second
        assert _wait(lambda: "arm_keepalive_p99_ms" in arm.telemetry(), 2.0) is not None
        assert set(calls) == {"jog", "stop_arm"}  # the test's own, and none for telemetry


def test_a_killed_arm_process_is_stopped_by_the_controller_and_the_node_reconnects():
    with _jogging_simulated_arm() as (arm, sim):
        trips = sim.stats()["watchdog_trips"]
        arm.kill()
        stopped = _wait(lambda: _at_rest(sim), 2.0)
        assert stopped is not None and stopped < 2 * WINDOW_S + DECEL_S, stopped
        assert sim.stats()["watchdog_trips"] == trips + 1  # the controller's own stop
        assert arm.needs_reconnect
        arm.disconnect()  # what the node's recovery does: a new arm process (and, for this
        arm.connect()  # kind, a new simulated controller)
        sim = arm.local.sim
        arm.jog(JOG)
        assert _wait(lambda: not _at_rest(sim), 2.0) is not None
        arm.stop()
        assert _wait(lambda: _at_rest(sim), 1.0) is not None


@pytest.mark.untimed  # no clock: a closed mapping read
def test_the_state_read_while_the_recovery_closes_it_is_empty_not_an_error():
    """The node's loop reads the arm process's state (its heartbeat's stats) while the
    recovery's thread closes the view: in CI a ``ValueError: mmap closed`` from that read
    ended the robot node's loop, and no jog moved the arm again."""
    from robot_side.arm.process.state import StateView, new_state_file

    path = new_state_file()
    try:
        writer, reader = StateView(path), StateView(path)
        writer.write({"t_write_s": 1.0})
        assert reader.read()["t_write_s"] == 1.0
        reader.close()
        assert reader.read() == {}
        writer.close()
    finally:
        path.unlink(missing_ok=True)


def test_an_arm_process_killed_from_outside_is_said_with_its_signal():
    """The node's error (and its log) says how its arm process ended: a crash in the driver
    (SIGSEGV, SIGABRT) reads differently from a kill or an exit."""
    with _jogging_simulated_arm() as (arm, _sim):
        os.kill(arm.pid, signal.SIGKILL)
        assert _wait(lambda: arm.needs_reconnect, 5.0) is not None
        with pytest.raises(DeviceError, match=r"the arm process ended \(killed by SIGKILL\)"):
            arm.jog(JOG)
