"""ur-rtde's watchdog: the UR simulator trips it as the control script would, the driver arms it.

The simulator runs in its own process; ur-rtde's own clients talk to it, so
what is tested is the wire: ``setWatchdog`` (command 35, the frequency in
``input_double_register_0``) and every package that carries
``input_int_register_0`` (a kick, or any command) as an update.
"""

from __future__ import annotations

import dataclasses
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from tests_support import wait_until

from common.devices.lifecycle import at_niceness
from common.errors import ConfigError, DeviceError
from robot_side.arm.base import NATIVE_DRIVER_THREAD_NICE, SAFETY_THREAD_NICE, ArmLimits
from robot_side.arm.ur_rtde import URArm, URArmConfig

pytestmark = [
    pytest.mark.slow,
    pytest.mark.timeout(60),
    pytest.mark.usefixtures("robot_node_priority_module"),
]

JOG = [0.03, 0.0, 0.0, 0.0, 0.0, 0.0]


@pytest.fixture(scope="module")
def receive(sim):
    import rtde_receive

    r = rtde_receive.RTDEReceiveInterface(sim.host)
    yield r
    r.disconnect()


def _speed(receive) -> float:
    return float(np.linalg.norm(receive.getActualTCPSpeed()[:3]))


def _program_running(receive) -> bool:
    return bool(int(receive.getRobotStatus()) & 2)


def test_no_update_for_one_period_stops_the_program_and_the_arm(sim, receive):
    import rtde_control

    ctrl = rtde_control.RTDEControlInterface(sim.host)
    try:
        assert ctrl.setWatchdog(10.0)
        assert sim.stats()["watchdog_hz"] == 10.0
        trips = sim.stats()["watchdog_trips"]
        assert ctrl.speedL(JOG, 0.5, 0.0)
        for _ in range(25):  # kicks alone keep it running for longer than the window ...
            assert ctrl.kickWatchdog()
            time.sleep(0.02)
        for _ in range(5):  # ... and so do commands: any package with the register counts
            assert ctrl.speedL(JOG, 0.5, 0.0)
            time.sleep(0.05)
        assert _program_running(receive) and _speed(receive) == pytest.approx(0.03)
        assert sim.stats()["watchdog_trips"] == trips
        t_last = time.monotonic()
        assert ctrl.kickWatchdog()
        # silence: the program stops 100 ms after the last update and the arm decelerates
        assert wait_until(lambda: not _program_running(receive), 2.0)
        t_stopped = time.monotonic() - t_last
        assert wait_until(lambda: _speed(receive) == 0.0, 1.0)
        t_still = time.monotonic() - t_last
        assert sim.stats()["watchdog_trips"] == trips + 1
        # not before the window (give or take the 2 ms controller cycle it is judged on)
        assert t_stopped >= 0.095, f"tripped {t_stopped * 1000:.0f} ms after the last kick"
        # a generous upper bound: only this machine's load can make it later than 100 ms
        assert t_still < 0.4, f"still only {t_still * 1000:.0f} ms after the last kick"
        # a stopped program takes no command, and the watchdog went with it (ur-rtde judges
        # from its own copy of the controller's state, a package or two behind under load)
        assert wait_until(lambda: not ctrl.speedL(JOG, 0.5, 0.0), 1.0)
        assert sim.stats()["watchdog_hz"] is None
        time.sleep(0.1)
        assert _speed(receive) == 0.0, "a command moved the arm after the program stopped"
    finally:
        ctrl.stopScript()
        ctrl.disconnect()


def test_a_new_program_starts_without_a_watchdog_and_a_stopped_arm(sim, receive):
    import rtde_control

    ctrl = rtde_control.RTDEControlInterface(sim.host)
    try:
        assert ctrl.setWatchdog(10.0)
        assert ctrl.speedL(JOG, 0.5, 0.0)
        assert wait_until(lambda: not _program_running(receive), 2.0)  # never kicked
        ctrl.disconnect()
        ctrl = rtde_control.RTDEControlInterface(sim.host)  # a new script, as a reconnect
        assert _program_running(receive)
        time.sleep(0.3)  # three windows with nothing sent: no watchdog armed, no trip
        assert _program_running(receive) and sim.stats()["watchdog_hz"] is None
        assert _speed(receive) == 0.0, "the new script ran the old program's speedL"
    finally:
        ctrl.stopScript()
        ctrl.disconnect()


LIMITS = ArmLimits(max_linear_speed_m_s=0.10, linear_acceleration_m_s2=1.0, jog_timeout_s=0.3)


@pytest.fixture
def arm(sim):
    limits = dataclasses.replace(LIMITS)  # a test may change its own
    a = URArm(URArmConfig(host=sim.host, limits=limits, stale_after_s=0.5))
    a.connect()
    yield a
    a.disconnect()


def _quiet_for_a_while(arm: URArm, sim, receive) -> tuple[bool, dict]:
    """Idle, a move (which sends nothing while it runs) and a jog: did the watchdog trip?"""
    trips = sim.stats()["watchdog_trips"]
    time.sleep(0.6)  # idle: only the kicks speak
    arm.move_to(arm.tcp_pose() + np.array([0.01, 0, 0, 0, 0, 0]), speed=0.05)
    arm.jog(JOG)
    time.sleep(0.2)
    arm.stop()
    return sim.stats()["watchdog_trips"] == trips and _program_running(receive), arm.status()


def test_the_driver_arms_the_watchdog_and_its_deadman_thread_keeps_it_quiet(arm, sim, receive):
    assert sim.stats()["watchdog_hz"] == pytest.approx(1 / arm.config.watchdog_window_s)
    quiet, status = _quiet_for_a_while(arm, sim, receive)
    window_ms = arm.config.watchdog_window_s * 1000
    if not quiet and status["longest_silence_ms"] > window_ms:
        # this process was stalled longer than the window (the machine's load, not the
        # driver): the controller did its job. Reconnect and measure once more
        first = status["longest_silence_ms"]
        arm.disconnect()
        arm.connect()
        quiet, status = _quiet_for_a_while(arm, sim, receive)
        status["first_try_silence_ms"] = first
    assert quiet, f"the watchdog tripped under a live driver: {status}"
    assert status["watchdog_kicks"] > 20 and "program_lost" not in status
    assert status["longest_silence_ms"] < window_ms, status


def test_the_keep_alive_kicks_until_a_disconnects_stop_is_on_the_wire(
    arm, sim, receive, monkeypatch
):
    """A disconnect (the arm process ending when its node died) stops the arm before it ends
    the kicks: a stop that reaches the wire late, here 0.3 s, twice the watchdog window, as
    on a busy PC, leaves the controller nothing to trip on; the arm process stopped it."""
    arm.jog(JOG)
    assert wait_until(lambda: _speed(receive) > 0.0, 1.0)
    trips = sim.stats()["watchdog_trips"]
    stop = arm._stop_locked

    def late_stop() -> None:
        time.sleep(2 * arm.config.watchdog_window_s)
        stop()

    monkeypatch.setattr(arm, "_stop_locked", late_stop)
    arm.disconnect()
    assert wait_until(lambda: _speed(receive) == 0.0, 1.0), "the disconnect left the arm moving"
    assert sim.stats()["watchdog_trips"] == trips, "the kicks ended before the stop"
    assert not _program_running(receive), "stopScript did not end the program"


def test_a_disconnects_own_end_of_the_script_is_not_reported_as_a_trip(
    arm, sim, receive, monkeypatch, caplog
):
    """The arm process's state writer asks ``needs_reconnect`` every 50 ms, also while a
    disconnect ends the script: the stopped script it then sees is this process's own doing,
    not a watchdog trip (a demo's shutdown logged one). A PC slow to close its receive
    interface after stopScript, as a busy one is, leaves the stop in view for 0.2 s here."""
    close = arm.receive.close

    def slow_close():
        time.sleep(0.2)
        return close()

    monkeypatch.setattr(arm.receive, "close", slow_close)
    polled = threading.Event()
    done = threading.Event()

    def poll() -> None:
        while not done.is_set():
            if arm.is_connected:
                arm.needs_reconnect  # noqa: B018 - the state writer's question
                polled.set()
            time.sleep(0.002)

    poller = threading.Thread(target=poll, daemon=True)
    poller.start()
    assert polled.wait(2.0)
    with caplog.at_level("WARNING"):
        arm.disconnect()
    done.set()
    poller.join(1.0)
    assert not _program_running(receive), "stopScript did not end the program"
    trips = [r.getMessage() for r in caplog.records if "stopped with the safety mode" in r.message]
    assert not trips, f"the disconnect's own stopScript was reported as a trip: {trips}"


def test_the_threads_that_stop_and_kick_run_at_the_robot_nodes_priority(arm):
    """A driver in a process at ordinary priority (a test, a tool) still kicks on a busy machine."""
    names = ("URArm-deadman", "URArm-keepalive", f"urarm-ctrl-{arm.config.host}")
    threads = {t.name: t.native_id for t in threading.enumerate() if t.name in names}
    assert sorted(threads) == sorted(names)
    mine = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    expected = SAFETY_THREAD_NICE if os.geteuid() == 0 else mine
    assert {n: os.getpriority(os.PRIO_PROCESS, tid) for n, tid in threads.items()} == dict.fromkeys(
        names, expected
    )


def test_ur_rtdes_own_threads_run_below_the_python_threads_that_drive_them(sim):
    """Its receive loops never take the GIL: at the unit's -10, their polling stands in front
    of no safety thread, and their wait for a CPU stops no Python thread."""
    mine = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    before = _thread_ids()
    arm = URArm(URArmConfig(host=sim.host, limits=dataclasses.replace(LIMITS), stale_after_s=0.5))

    def connect() -> int:  # from a thread at the robot node's -15, as the node connects
        arm.connect()
        return os.getpriority(os.PRIO_PROCESS, threading.get_native_id())

    creator = at_niceness(SAFETY_THREAD_NICE, connect)()
    try:
        python = {t.native_id for t in threading.enumerate()}
        native = _thread_ids() - before - python
        assert native, "ur-rtde started no thread of its own"
        expected = max(creator, NATIVE_DRIVER_THREAD_NICE)  # lowered, never raised
        assert {tid: os.getpriority(os.PRIO_PROCESS, tid) for tid in native} == dict.fromkeys(
            native, expected
        )
        assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == mine
    finally:
        arm.disconnect()


def _thread_ids() -> set[int]:
    return {int(t) for t in os.listdir("/proc/self/task")}


def test_a_silent_driver_is_stopped_by_the_controller_and_recovers_by_reconnecting(
    arm, sim, receive, caplog
):
    arm.limits.jog_timeout_s = 5.0  # only the watchdog may stop this jog
    arm.jog(JOG)
    assert wait_until(lambda: _speed(receive) == pytest.approx(0.03), 1.0)
    # the deadman thread falls silent, as when the process freezes (SIGSTOP, a wedged GIL)
    arm._keep_alive = lambda: None
    assert wait_until(lambda: not _program_running(receive), 1.0)
    assert wait_until(lambda: _speed(receive) == 0.0, 1.0)
    with caplog.at_level("WARNING", logger="robot_side.arm.ur_rtde"):
        del arm._keep_alive  # the thread is alive again: it notices the stopped program
        assert wait_until(lambda: arm.needs_reconnect, 1.0)
        # the thread logs what it noticed right after it marks the program lost
        assert wait_until(lambda: "last two turns" in caplog.text, 1.0), caplog.text
    assert "program_lost" in arm.status()
    # a warning says which silence it was: no call held the wire, the kicks did not run (on a
    # busy machine the thread may turn twice before it notices: the kick's own warning says it)
    said = re.search(
        r"a call does not hold the wire; the keep-alive thread's last two turns were (\d+) and",
        caplog.text,
    )
    heard = re.search(r"the controller heard nothing from this process for (\d+) ms", caplog.text)
    assert any(m and int(m[1]) > 150 for m in (said, heard)), caplog.text
    with pytest.raises(DeviceError, match="stopped with the safety mode normal"):
        arm.jog(JOG)
    arm.stop()  # the controller stopped the arm: nothing to tell it, no error
    with pytest.raises(DeviceError, match="Reconnect"):
        arm.telemetry()  # what makes the node's arm worker start its recovery at once
    time.sleep(0.2)
    assert _speed(receive) == 0.0, "moved on a command sent to the stopped program"
    arm.disconnect()
    arm.connect()
    assert not arm.needs_reconnect and sim.stats()["watchdog_hz"] == pytest.approx(1 / 0.15)
    assert _speed(receive) == 0.0
    arm.jog(JOG)  # a fresh command moves it again
    assert wait_until(lambda: _speed(receive) > 0.0, 1.0)
    arm.stop()


def test_a_starved_deadman_leaves_its_jog_to_the_controller_and_the_box_holds(arm, sim, receive):
    """One jog toward a face 5 mm away, then the deadman thread starves (held in its turn).

    No kick vouches for a jog past its deadline: the controller's watchdog
    stops the arm, and the jog was clipped for that later stop
    (``jog_backstop_s``), so the TCP ends short of the face, seen on the
    controller. Clipped for the deadman's stop alone, it went 0.7 mm past.
    """
    limits = arm.limits
    y = float(sim.tcp_pose()[1])
    limits.workspace_max = (limits.workspace_max[0], y + 0.005, limits.workspace_max[2])
    trips = sim.stats()["watchdog_trips"]
    go_on = threading.Event()
    try:
        sent = arm.jog([0.0, 1.0, 0.0, 0.0, 0.0, 0.0])  # once, toward +y
        arm._watch_spins = lambda: go_on.wait(10.0)  # its next turn never ends
        assert sent[1] > 0.005, sent
        assert wait_until(lambda: not _program_running(receive), 2.0), "no watchdog trip"
        assert wait_until(lambda: _speed(receive) == 0.0, 1.0)
        assert sim.stats()["watchdog_trips"] == trips + 1
        assert arm.status()["deadman_stops"] == 0, "the deadman stopped it: it was not starved"
        reached = float(sim.tcp_pose()[1]) - y
        assert reached <= 0.005 + 1e-5, f"{reached * 1000:.2f} mm: past the face at 5 mm"
        assert reached > 0.002, f"the jog hardly moved toward the face ({reached * 1000:.2f} mm)"
    finally:
        go_on.set()
        del arm._watch_spins


def test_a_stop_on_the_dashboard_is_noticed_and_a_move_reconnects_first(arm, sim, receive):
    with socket.create_connection((sim.host, 29999), timeout=2) as dash:
        f = dash.makefile("rwb")
        f.readline()
        f.write(b"stop\n")
        f.flush()
        assert f.readline().strip() == b"Stopped"
    assert wait_until(lambda: arm.needs_reconnect, 1.0)
    with pytest.raises(DeviceError, match="pendant or the dashboard"):
        arm.jog(JOG)
    # a move is an absolute target asked for now: it reconnects (a fresh script) and moves
    target = arm.tcp_pose() + np.array([0.0, 0.01, 0, 0, 0, 0])
    arm.move_to(target, speed=0.05)
    assert not arm.needs_reconnect
    np.testing.assert_allclose(arm.tcp_pose()[:3], target[:3], atol=1e-4)


@pytest.mark.parametrize(
    ("section", "why"),
    [
        ({"watchdog_window_s": 0.2}, "no time to decelerate within the 400 ms"),
        ({"watchdog_window_s": 0.0}, "cannot be turned off"),
        ({"watchdog_window_s": 0.05}, "less than three kicks"),
        ({"limits": ArmLimits(stop_deceleration_m_s2=0.6)}, "as long as the watchdog window"),
    ],
)
def test_a_watchdog_that_cannot_work_is_refused_at_construction(section, why):
    with pytest.raises(ConfigError, match=why):
        URArm(URArmConfig(**section))


def test_a_stop_from_the_wrists_top_speed_ends_before_the_watchdog_window(sim, receive):
    """A stop waits for the script and no kick may interrupt it: it must end inside the window.

    The controller decelerates a rotation at the stop's one acceleration, in rad/s^2
    (URScript's ``stopl(a)``: ``aRot`` defaults to ``a``). A stop from the angular cap that
    outlasted the watchdog window tripped the watchdog on every fast wrist turn (the lab's
    task trials lost the arm that way, a few times per 50 trials).
    """
    limits = ArmLimits()  # the defaults a lab runs with
    arm = URArm(URArmConfig(host=sim.host, limits=limits, stale_after_s=0.5))
    arm.connect()
    try:
        trips = sim.stats()["watchdog_trips"]
        top = limits.max_angular_speed_rad_s
        for _ in range(3):
            deadline = time.monotonic() + 3.0
            while abs(receive.getActualTCPSpeed()[4]) < 0.95 * top:  # held, as a jog is
                assert time.monotonic() < deadline, "the wrist never reached its top speed"
                arm.jog([0, 0, 0, 0, top, 0])
                time.sleep(0.05)
            arm.stop()
            assert wait_until(lambda: abs(receive.getActualTCPSpeed()[4]) == 0.0, 1.0)
        status = arm.status()
        assert sim.stats()["watchdog_trips"] == trips, f"the stop tripped the watchdog: {status}"
        assert status["longest_silence_ms"] < arm.config.watchdog_window_s * 1000, status
    finally:
        arm.disconnect()


def test_a_watchdog_that_trips_while_it_is_armed_is_armed_again(sim, receive, monkeypatch, caplog):
    """The controller counts the window from the moment it arms the watchdog; ur-rtde's next
    update goes out once this process has read the script's answer. A process that reads it
    late (a busy robot PC starting its node; here the controller's stream held back 0.4 s)
    loses the script to the watchdog before its first kick: connect arms it again."""
    import rtde_control

    class AnswerReadLate(rtde_control.RTDEControlInterface):
        late = 1

        def setWatchdog(self, min_frequency):
            if AnswerReadLate.late:
                AnswerReadLate.late -= 1
                sim.freeze()
                threading.Timer(0.4, sim.freeze, args=(False,)).start()
            return super().setWatchdog(min_frequency)

    monkeypatch.setattr(rtde_control, "RTDEControlInterface", AnswerReadLate)
    trips = sim.stats()["watchdog_trips"]
    arm = URArm(URArmConfig(host=sim.host, limits=dataclasses.replace(LIMITS), stale_after_s=0.5))
    with caplog.at_level("WARNING", logger="robot_side.arm.ur_rtde"):
        arm.connect()
    try:
        assert AnswerReadLate.late == 0, "the controller's answer was never held back"
        assert sim.stats()["watchdog_trips"] == trips + 1, "the held-back answer did not trip"
        assert "stopped while it armed the watchdog" in caplog.text
        assert "connecting again (2 of 3)" in caplog.text
        assert sim.stats()["watchdog_hz"] == pytest.approx(1 / arm.config.watchdog_window_s)
        assert _program_running(receive) and not arm.needs_reconnect
        arm.jog(JOG)  # the second script is the one that moves
        assert wait_until(lambda: _speed(receive) > 0.0, 1.0)
        arm.stop()
        assert wait_until(lambda: _speed(receive) == 0.0, 1.0)
    finally:
        arm.disconnect()


#: the watchdog's window in the killed-client test: long enough that the client's kicks, from
#: an ordinary process on a loaded machine, never miss it
KILLED_CLIENT_WINDOW_S = 0.5

#: a client that arms the watchdog, jogs and kicks until it is killed (armed again if it
#: tripped before the first kick, as the driver does on a busy machine)
#: a client that jogs as the driver does: the jog renewed every 20 ms (each renewal an update
#: of the watchdog's register), so a jog the script never read (the register written again
#: before the controller's next cycle, on a loaded machine) is made good by the next
JOGGING_CLIENT = """
import sys, time, rtde_control
c = rtde_control.RTDEControlInterface(sys.argv[1])
jog = lambda: c.speedL([0.03, 0, 0, 0, 0, 0], 0.5, 0.0)
for _ in range(3):
    assert c.setWatchdog(1 / float(sys.argv[2])) and jog()
    for _ in range(10):
        jog()
        time.sleep(0.02)
    if c.isProgramRunning():
        break
    c.reuploadScript()
else:
    sys.exit("the program never kept running")
print("jogging", flush=True)
while True:
    jog()
    time.sleep(0.02)
"""


def test_a_killed_client_is_stopped_in_its_window_while_the_simulator_is_starved():
    """A starved simulator does not count its own stalls against a connected client, but a
    client whose process died waits on nothing: the watchdog counts the wall time, as the
    controller does (a killed arm process's arm ran on for a second when a simulator starved
    by a loaded machine counted 20 ms a tick, 150 ms in eight of them)."""
    from robot_side.arm.sim import URSimProcess

    window = KILLED_CLIENT_WINDOW_S
    sim = URSimProcess().start()
    client = subprocess.Popen(
        [sys.executable, "-c", JOGGING_CLIENT, sim.host, str(window)],
        stdout=subprocess.PIPE,
        text=True,
    )
    starving = threading.Event()

    def starve() -> None:  # 10 ms of the CPU in every 160 ms
        while not starving.is_set():
            os.kill(sim.pid, signal.SIGSTOP)
            time.sleep(0.15)
            os.kill(sim.pid, signal.SIGCONT)
            time.sleep(0.01)

    starver = threading.Thread(target=starve, daemon=True)
    try:
        assert client.stdout.readline().strip() == "jogging", "the client never jogged"
        jogging = wait_until(lambda: sim.tcp_speed()[0] == pytest.approx(0.03), 2.0)
        assert jogging, (sim.tcp_speed(), sim.stats())
        trips = sim.stats()["watchdog_trips"]
        t_killed = time.monotonic()
        client.kill()
        starver.start()
        time.sleep(window + 1.5)
        starving.set()
        starver.join()
        os.kill(sim.pid, signal.SIGCONT)
        stats = sim.stats()
        # counted 20 ms a tick, the window would take about 2.9 s of this starving
        assert stats["watchdog_trips"] == trips + 1, stats
        tripped = stats["watchdog_tripped_at_s"] - t_killed
        # counted from the client's last update, a renewal (20 ms, later on a busy machine)
        # before its kill at most; at the first tick after the window, the next stretch of
        # CPU at worst
        assert window - 0.1 <= tripped <= window + 0.4, (
            f"the watchdog tripped {tripped * 1e3:.0f} ms after its client was killed, window "
            f"{window * 1e3:.0f} ms, the simulator stalled 150 ms at a time"
        )
        assert wait_until(lambda: not sim.tcp_speed().any(), 1.0), "the arm moves on"
    finally:
        starving.set()
        if starver.is_alive():
            starver.join()
        os.kill(sim.pid, signal.SIGCONT)
        client.kill()
        client.wait()
        sim.stop()


def test_a_kick_spinning_on_a_hung_script_leaves_real_time_until_it_returns():
    """ur-rtde's kick waits for the script's "ready" in a loop without sleeping (up to its own
    timeout, seconds); at the keep-alive's SCHED_FIFO it would hold a core from the machine.

    The simulated script stops reading commands and saying "ready" (and its watchdog then
    stops the program); the keep-alive thread is read back from the kernel: fair while the
    kick spins, real-time again once ur-rtde gave up. Where this process may not run
    real-time, nothing spins at SCHED_FIFO and nothing is moved.
    """
    from robot_side.arm.sim import URSimProcess

    with URSimProcess() as sim:
        arm = URArm(URArmConfig(host=sim.host, stale_after_s=0.5))
        arm.realtime_priority = 5
        arm.connect()
        try:
            assert wait_until(lambda: arm.keep_alive_scheduling is not None, 2.0)
            tid = arm._keep_alive_thread.native_id
            sim.hang_script()
            if not arm.keep_alive_scheduling.realtime:
                time.sleep(0.5)
                assert arm.line.spin_guard.demotions == 0
                return
            # the kick holds the wire while ur-rtde waits (its timeout is seconds): fair
            # meanwhile, moved by the guard (or already fair: a kick that followed the script's
            # last answer too closely goes from the fair scheduler, on a loaded machine too)
            spinning_fair = lambda: (  # noqa: E731
                arm.line.wire.locked() and os.sched_getscheduler(tid) == os.SCHED_OTHER
            )
            assert wait_until(spinning_fair, 2.0), arm.status()
            assert wait_until(lambda: os.sched_getscheduler(tid) == os.SCHED_FIFO, 10.0)
            assert arm.status()["spins_made_fair"] == arm.line.spin_guard.demotions
        finally:
            sim.hang_script(False)
            arm.disconnect()
