"""The real URArm driver (ur-rtde's own clients) against the UR simulator, over TCP.

Each simulator runs in its own process on its own loopback address (ur-rtde's
ports are fixed). Clients are always disconnected before their simulator
stops, except where a test makes the controller vanish on purpose. ur-rtde's
destructors sleep 0.5 s each, so arms are shared where a test leaves them
clean.
"""

from __future__ import annotations

import socket
import struct
import time

import numpy as np
import pytest
from tests_support import wait_until

from common.clocks.clock import now_s
from common.config.typed import from_dict
from common.devices.lifecycle import build_device
from common.errors import (
    ConfigError,
    DeviceError,
    DeviceNotConnectedError,
    StaleDataError,
)
from robot_side.arm import KINDS
from robot_side.arm.base import ArmLimits, WorkspaceLimitError
from robot_side.arm.process import ArmProcess
from robot_side.arm.sim import URSimConfig, URSimProcess, URSimulator
from robot_side.arm.sim import rtde_wire as w
from robot_side.arm.ur_rtde import ArmCommandRefusedError, URArm, URArmConfig

pytestmark = [
    pytest.mark.timeout(30),
    # the heap frozen before the module's arm connects: a full collection holds the GIL the
    # keep-alive's kicks need (quiet_gc_module)
    pytest.mark.usefixtures("quiet_gc_module", "robot_node_priority_module"),
]

LIMITS = ArmLimits(
    workspace_min=(-0.45, -0.30, 0.05),
    workspace_max=(0.0, 0.10, 0.40),
    max_linear_speed_m_s=0.10,
    linear_acceleration_m_s2=1.0,
    jog_timeout_s=0.2,
)


#: The robot's 0.1 s staleness limit is for a controller streaming at 500 Hz; a simulator
#: sharing two cores with other test processes can pause longer than that.
STALE_S = 0.5


@pytest.fixture(scope="module")
def arm(sim):
    a = URArm(URArmConfig(host=sim.host, limits=LIMITS, stale_after_s=STALE_S))
    a.connect()
    yield a
    a.disconnect()  # before the module's simulator stops


@pytest.fixture
def still_arm(arm, sim):
    """The shared arm, guaranteed at rest before and after the test."""
    arm.stop()
    yield arm
    arm.stop()
    assert wait_until(lambda: sim.mode_name() == "idle", 2.0)


def test_reads_pose_and_joints_the_controller_reports(still_arm, sim):
    pose = still_arm.tcp_pose()
    q = still_arm.joint_positions()
    assert pose.shape == (6,) and q.shape == (6,)
    np.testing.assert_allclose(pose, sim.tcp_pose(), atol=1e-6)
    status = still_arm.status()
    assert status["connected"] and status["safety"] == "normal"
    assert status["program_running"] is True


def test_receive_streams_at_the_configured_rate(still_arm, sim):
    """The controller streams at the rate the driver asked for, counted where it sends (the
    simulator's packages over its RTDE clients: the receive and the control interface), and
    the driver's reads follow the stream. How many distinct packages this test's own sampling
    sees is the machine's, not the stream's: starved among busy workers, it samples every
    20 ms or so, so it only shows the stream moving."""
    asked = still_arm.config.frequency_hz
    before, t0 = sim.stats(), time.monotonic()
    first = last = still_arm.receive.controller_timestamp()
    seen = 1
    while time.monotonic() - t0 < 1.0:
        ts = still_arm.receive.controller_timestamp()
        seen, last = seen + (ts != last), ts
        time.sleep(0.0005)
    after, t1 = sim.stats(), time.monotonic()
    clients = after["rtde_clients"]
    rate = (after["data_packages_sent"] - before["data_packages_sent"]) / (t1 - t0) / clients
    # about the rate asked on an idle machine; a simulator starved on a loaded one sends less,
    # but never a trickle
    assert clients == 2 and rate > 0.4 * asked, f"{rate:.0f} packages/s to each client"
    assert seen >= 10 and last - first > 0.5, f"{seen} packages over {last - first:.2f} s"


def test_move_to_reaches_the_target_along_a_line(still_arm, sim):
    start = still_arm.tcp_pose()
    target = start.copy()
    target[:3] += [0.02, 0.01, 0.02]
    t0 = time.monotonic()
    still_arm.move_to(target, speed=0.1)
    took = time.monotonic() - t0
    np.testing.assert_allclose(still_arm.tcp_pose()[:3], target[:3], atol=1e-5)
    assert 3 in sim.commands_seen()  # moveL
    assert took < 4.0  # 0.5 s of motion; slack for a loaded machine
    still_arm.move_to(start, speed=0.1)


def test_move_outside_the_workspace_is_refused_before_anything_is_sent(still_arm, sim):
    def commands() -> list[int]:  # a watchdog kick writes 0 to the register: not a command
        return [c for c in sim.commands_seen() if c != 0]

    seen = len(commands())
    target = still_arm.tcp_pose()
    target[2] = 0.01  # below the table guard
    with pytest.raises(WorkspaceLimitError, match="outside the workspace box"):
        still_arm.move_to(target)
    assert len(commands()) == seen


@pytest.mark.slow
def test_move_speed_above_the_limit_is_clipped(still_arm, sim):
    start = still_arm.tcp_pose()
    target = start.copy()
    target[1] += 0.04
    still_arm.move_to(target, speed=2.0, wait=False)
    peak = 0.0
    while sim.mode_name() != "idle":
        peak = max(peak, float(np.linalg.norm(still_arm.receive.tcp_speed()[:3])))
        time.sleep(0.005)
    assert 0.05 < peak <= LIMITS.max_linear_speed_m_s + 1e-6
    still_arm.move_to(start)


def test_jog_is_clipped_to_the_speed_limit_and_stops_when_told(still_arm, sim):
    def fast_enough() -> bool:
        still_arm.jog([0.0, -1.0, 0.0, 0.0, 0.0, 0.0])  # 1 m/s asked, renewed
        return sim.tcp_speed()[1] < -0.09

    assert wait_until(fast_enough, 1.0)
    assert np.linalg.norm(sim.tcp_speed()[:3]) <= LIMITS.max_linear_speed_m_s + 1e-9
    assert sim.at_rest_since(1e-4, 1e-3) is None  # the controller's record: moving
    t_stop = time.monotonic()
    still_arm.stop()
    speed = sim.tcp_speed()
    assert np.allclose(speed, 0.0), _why_still_moving(still_arm, sim, speed)
    # ... and at rest since a moment between the stop's call and its return, on this clock
    rest = sim.at_rest_since(1e-4, 1e-3)
    assert rest is not None and t_stop < rest <= time.monotonic(), (t_stop, rest)
    at_rest = sim.tcp_pose()
    time.sleep(0.1)
    np.testing.assert_allclose(sim.tcp_pose(), at_rest, atol=1e-9)
    assert {10, 15} <= set(sim.commands_seen())  # speedL, speedStop


def _why_still_moving(arm, sim, speed) -> str:
    """What the controller and the driver each say when a returned stop left the arm moving."""
    stats = sim.stats()
    keys = ("mode", "program_running", "watchdog_trips", "program_ends", "scripts_received")
    return (
        f"TCP speed {np.round(speed, 4).tolist()} after stop() returned; controller: "
        f"{ {k: stats[k] for k in keys} }, commands {sim.commands_seen()[-12:]}; driver: "
        f"{arm.status()}"
    )


def test_deadman_stops_a_jog_that_is_not_renewed(still_arm, sim):
    stops = still_arm.status()["deadman_stops"]
    still_arm.jog([0.0, 0.0, 0.02, 0.0, 0.0, 0.0])
    assert wait_until(lambda: sim.tcp_speed()[2] > 0.015, 0.5)
    assert wait_until(lambda: sim.mode_name() == "idle", LIMITS.jog_timeout_s + 0.5)
    assert still_arm.status()["deadman_stops"] == stops + 1


def test_renewed_jogs_keep_the_arm_moving(still_arm, sim):
    end = time.monotonic() + 3 * LIMITS.jog_timeout_s
    while time.monotonic() < end:
        still_arm.jog([0.0, 0.0, -0.02, 0.0, 0.0, 0.0])
        time.sleep(LIMITS.jog_timeout_s / 3)
    assert sim.mode_name() == "speedL"
    still_arm.stop()
    assert sim.mode_name() == "idle"


def test_jog_cannot_push_out_of_the_box_but_can_come_back(still_arm):
    pose = np.array([0.0, 0.0, 0.2, 0.0, 3.14, 0.0])  # on the +x face
    out = still_arm.clip_jog([0.05, 0.01, 0.0, 0.0, 0.0, 0.0], pose)
    assert out[0] == 0.0 and out[1] == pytest.approx(0.01)
    back = still_arm.clip_jog([-0.05, 0.0, 0.0, 0.0, 0.0, 0.0], pose)
    assert back[0] == pytest.approx(-0.05)
    spin = still_arm.clip_jog([0, 0, 0, 0, 0, 5.0], pose)
    assert spin[5] == pytest.approx(LIMITS.max_angular_speed_rad_s)
    with pytest.raises(ValueError, match="finite"):
        still_arm.clip_jog([float("nan"), 0, 0, 0, 0, 0], pose)


def test_one_jog_toward_a_face_cannot_carry_the_tcp_past_it_before_its_deadman(still_arm, sim):
    """No fresher jog comes (a starved node): the box holds all the same, seen on the controller.

    A jog at the cap 5 mm from a face used to run its whole lifetime (20 mm) past it;
    clipped to the jog's reach (lifetime, deadman period, stop transit and deceleration)
    it ends short of the face.
    """
    limits = still_arm.limits
    saved = limits.workspace_max
    y = float(sim.tcp_pose()[1])
    limits.workspace_max = (saved[0], y + 0.005, saved[2])
    try:
        still_arm.jog([0.0, 1.0, 0.0, 0.0, 0.0, 0.0])  # once, at the cap, toward +y
        assert wait_until(lambda: sim.tcp_speed()[1] > 0.005, 1.0), "the jog never moved it"
        assert wait_until(lambda: sim.mode_name() == "idle", limits.jog_timeout_s + 1.0)
        reached = float(sim.tcp_pose()[1])
        assert reached <= y + 0.005 + 1e-5, f"{(reached - y) * 1000:.2f} mm: past the face at 5"
        assert reached > y + 0.002, "the jog hardly moved toward the face"
    finally:
        limits.workspace_max = saved


def test_the_controller_accounts_for_when_it_read_ran_and_answered_each_stop(still_arm, sim):
    """The simulator's own account of a jog's stop (what a late stop's test prints): the
    speedL to rest arrives and runs, then speedStop arrives, runs and is answered "done"."""
    t0 = time.monotonic()
    still_arm.jog([0.0, 0.0, -0.02, 0.0, 0.0, 0.0])
    assert wait_until(lambda: sim.tcp_speed()[2] < -0.01, 1.0)
    still_arm.stop()
    events = sim.command_events(t0)
    assert all(t >= t0 for t, _, _ in events), events
    assert [t for t, _, _ in events] == sorted(t for t, _, _ in events), events
    said = [(cmd, what) for _, cmd, what in events]
    assert (10, "arrived at 0.020 m/s") in said, said  # the jog's speedL
    rest = said.index((10, "arrived at 0.000 m/s"))  # the speedL to rest ...
    assert said[rest + 1] == (10, "ran"), said  # ... acted on before anything else came
    stop = said.index((15, "arrived"), rest)  # then speedStop, acted on and answered
    assert said[stop + 1 : stop + 3] == [(15, "ran"), (15, "done")], said


def test_stop_is_idempotent(still_arm, sim):
    still_arm.stop()
    still_arm.stop()
    assert sim.mode_name() == "idle"


#: ur-rtde's disconnect() sleeps 0.5 s on each of the two interfaces: side by side about 0.5 s,
#: one after the other 1.0 s
DISCONNECT_WITHIN_S = 0.9


def test_disconnect_closes_both_interfaces_side_by_side_and_the_next_session_follows():
    with URSimProcess() as own:  # the module's arm holds the shared simulator's inputs
        arm = URArm(URArmConfig(host=own.host, limits=LIMITS, stale_after_s=STALE_S))
        arm.connect()
        t0 = time.monotonic()
        arm.disconnect()
        took = time.monotonic() - t0
        assert 0.5 <= took < DISCONNECT_WITHIN_S, f"disconnect took {took:.3f} s"
        arm.connect()  # the controller took both closes: the next session is not refused
        try:
            assert np.isfinite(arm.tcp_pose()).all()
        finally:
            arm.disconnect()


def test_limits_config_refuses_an_inverted_box():
    with pytest.raises(ConfigError, match="below workspace_max"):
        from_dict(ArmLimits, {"workspace_min": [0.5, 0, 0], "workspace_max": [0.1, 1, 1]})


def test_not_connected_arm_says_so():
    arm = URArm(URArmConfig(host="127.0.0.1"))
    with pytest.raises(DeviceNotConnectedError, match="call connect"):
        arm.tcp_pose()
    arm.stop()  # safe, does nothing
    arm.disconnect()


def test_no_controller_at_the_address_is_a_clear_error():
    arm = URArm(URArmConfig(host="127.0.3.1"))  # outside the simulators' 127.0.0.x pool
    t0 = time.monotonic()
    with pytest.raises(DeviceNotConnectedError, match="is on, reachable"):
        arm.connect()
    assert time.monotonic() - t0 < 5.0
    assert not arm.is_connected


@pytest.mark.slow
def test_stale_stream_is_an_error_not_a_repeat():
    with URSimProcess() as sim:
        arm = URArm(URArmConfig(host=sim.host, limits=LIMITS, stale_after_s=0.3))
        arm.connect()
        try:
            arm.tcp_pose()
            sim.freeze()
            t0 = time.monotonic()
            with pytest.raises(StaleDataError, match="stopped streaming"):
                while time.monotonic() - t0 < 2.0:
                    arm.tcp_pose()
                    time.sleep(0.01)
            assert time.monotonic() - t0 < 1.5  # 0.3 s limit; slack for a loaded machine
            with pytest.raises(StaleDataError):
                arm.jog([0.0, 0.0, 0.01, 0.0, 0.0, 0.0])  # never jog on old data
            sim.freeze(False)
            assert wait_until(lambda: _reads(arm), 1.0)
            assert arm.status()["stale_events"] >= 2
        finally:
            arm.disconnect()


def _reads(arm: URArm) -> bool:
    try:
        arm.tcp_pose()
    except StaleDataError:
        return False
    return True


@pytest.mark.slow
def test_protective_stop_refuses_jogs_with_the_reason():
    with URSimProcess() as sim:
        arm = URArm(URArmConfig(host=sim.host, limits=LIMITS, stale_after_s=STALE_S))
        arm.connect()
        try:
            arm.jog([0.0, 0.0, 0.01, 0.0, 0.0, 0.0])
            sim.protective_stop()
            assert wait_until(lambda: arm.status()["safety"] == "protective stop", 1.0)
            with pytest.raises(ArmCommandRefusedError, match="protective stop"):
                arm.jog([0.0, 0.0, 0.01, 0.0, 0.0, 0.0])
            with pytest.raises(ArmCommandRefusedError, match="protective stop"):
                arm.move_to(arm.tcp_pose())
            sim.unlock_protective_stop()  # cleared on the pendant ...
        finally:
            arm.disconnect()
        arm.connect()  # ... and a new control script uploaded
        try:
            arm.jog([0.0, 0.0, 0.01, 0.0, 0.0, 0.0])
            assert wait_until(lambda: sim.mode_name() == "speedL", 1.0)
            arm.stop()
        finally:
            arm.disconnect()


@pytest.mark.slow
def test_simulated_kind_runs_the_real_driver_and_survives_a_vanished_controller():
    section = {"kind": "simulated", "stale_after_s": STALE_S, "limits": {"jog_timeout_s": 0.3}}
    arm = build_device(KINDS, section, "arm")
    # the real driver in its arm process; the simulator, as a controller would, outside it
    assert isinstance(arm, ArmProcess) and type(arm.local).__name__ == "SimulatedArm"
    assert isinstance(arm.local, URArm)
    arm.connect()
    try:
        host = arm.local.sim.host
        arm.jog([0.0, 0.0, 0.01, 0.0, 0.0, 0.0])
        arm.local.sim.kill()  # the controller is gone: no FIN handshake, no goodbye
        t0 = time.monotonic()
        # refused either way: as a lost connection, or as a stale stream if its timestamp
        # stops for stale_after_s before the socket's loss is noticed (a loaded machine)
        with pytest.raises(
            (DeviceNotConnectedError, StaleDataError),
            match=r"lost the RTDE connection|has not advanced",
        ):
            while time.monotonic() - t0 < 2.0:
                arm.tcp_pose()
                time.sleep(0.01)
        with pytest.raises(DeviceError):
            arm.jog([0.0, 0.0, 0.01, 0.0, 0.0, 0.0])
        with pytest.raises(DeviceError):
            arm.stop()  # cannot be delivered: says so instead of hanging
        assert time.monotonic() - t0 < 5.0
    finally:
        t0 = time.monotonic()
        arm.disconnect()
        assert time.monotonic() - t0 < 5.0

    # reconnecting: a controller comes back on the same address
    with URSimProcess(URSimConfig(host=host)) as sim:
        again = URArm(URArmConfig(host=host, limits=LIMITS, stale_after_s=STALE_S))
        again.connect()
        try:
            np.testing.assert_allclose(again.tcp_pose(), sim.tcp_pose(), atol=1e-6)
        finally:
            again.disconnect()


def _rtde(sock: socket.socket, mtype: int, payload: bytes = b"") -> tuple[int, bytes]:
    sock.sendall(w.pack_message(mtype, payload))
    head = sock.recv(3, socket.MSG_WAITALL)
    size, rtype = w.HEADER.unpack(head)
    body = sock.recv(size - 3, socket.MSG_WAITALL) if size > 3 else b""
    return rtype, body


def test_simulator_speaks_rtde_like_a_controller():
    """A raw client: what a developer compares byte for byte with a real controller."""
    sim = URSimulator(URSimConfig(host="auto", tick_hz=125)).start()
    try:
        with socket.create_connection((sim.host, 30004), timeout=2) as s:
            assert _rtde(s, w.REQUEST_PROTOCOL_VERSION, struct.pack(">H", 2)) == (ord("V"), b"\x01")
            _, body = _rtde(s, w.GET_URCONTROL_VERSION)
            assert struct.unpack(">IIII", body)[0] == 5
            _, body = _rtde(s, w.SETUP_OUTPUTS, struct.pack(">d", 125.0) + b"timestamp,bogus")
            assert body == b"\x00DOUBLE,NOT_FOUND"
            _, body = _rtde(s, w.SETUP_OUTPUTS, struct.pack(">d", 125.0) + b"timestamp,actual_q")
            assert body == b"\x01DOUBLE,VECTOR6D"
            _, body = _rtde(s, w.SETUP_INPUTS, b"input_int_register_0")
            assert body == b"\x01INT32"  # input ids count separately from output ids
            assert _rtde(s, w.START) == (ord("S"), b"\x01")
            size, rtype = w.HEADER.unpack(s.recv(3, socket.MSG_WAITALL))
            body = s.recv(size - 3, socket.MSG_WAITALL)
            assert rtype == w.DATA_PACKAGE and body[0] == 1
            ts, *q = struct.unpack(">d6d", body[1:])
            assert ts >= 0.0
            np.testing.assert_allclose(q, URSimConfig().home_q)
        with socket.create_connection((sim.host, 29999), timeout=2) as d:
            f = d.makefile("rwb")
            assert f.readline().startswith(b"Connected: Universal Robots Dashboard Server")
            f.write(b"get serial number\n")
            f.flush()
            assert f.readline().strip().isdigit()
    finally:
        sim.stop()


def _streamed_tcp_pose(s: socket.socket) -> np.ndarray:
    """The newest actual_TCP_pose a started raw client has been sent."""
    s.setblocking(False)
    try:  # drop what queued up while the test waited
        while s.recv(65536):
            pass
    except BlockingIOError:
        pass
    s.setblocking(True)
    while True:
        size, rtype = w.HEADER.unpack(s.recv(3, socket.MSG_WAITALL))
        body = s.recv(size - 3, socket.MSG_WAITALL)
        if rtype == w.DATA_PACKAGE and len(body) == 1 + 6 * 8:
            return np.array(struct.unpack(">6d", body[1:]))


def test_an_external_motion_clock_moves_the_arm_only_by_the_time_its_owner_steps():
    """The lab world's one clock: the wire streams in real time, the arm waits for advance()."""
    with pytest.raises(ConfigError, match="motion_clock"):
        URSimulator(URSimConfig(motion_clock="sim"))
    sim = URSimulator(URSimConfig(host="auto", motion_clock="external")).start()
    try:
        with pytest.raises(ConfigError, match="external"):
            URSimulator(URSimConfig()).advance(0.1)
        with socket.create_connection((sim.host, 30004), timeout=2) as s:
            _rtde(s, w.REQUEST_PROTOCOL_VERSION, struct.pack(">H", 2))
            _rtde(s, w.SETUP_OUTPUTS, struct.pack(">d", 125.0) + b"actual_TCP_pose")
            assert _rtde(s, w.START) == (ord("S"), b"\x01")
            start = _streamed_tcp_pose(s)
            with sim.lock:  # what a speedL makes the control script do
                sim.arm.speed_l(np.array([0.0, 0.0, 0.05, 0.0, 0.0, 0.0]), 10.0)
            time.sleep(0.3)
            waited = _streamed_tcp_pose(s)
            np.testing.assert_allclose(waited, start, atol=1e-9, err_msg="wall time moved it")
            for _ in range(20):  # 0.2 s of the owner's time, in its 10 ms loops
                sim.advance(0.01)
            moved = _streamed_tcp_pose(s)[2] - start[2]
        # 0.05 m/s for 0.2 s (its 5 ms ramp inside the first step), not for the 0.5 s that passed
        assert moved == pytest.approx(0.05 * 0.2, abs=2e-4)
        # the RTDE watchdog counts the same clock: 0.3 s of wall is no silence, 0.2 s of it is
        with sim.lock:  # what setWatchdog(10 Hz) makes the running script do
            sim.script.program_running, sim.script.watchdog_hz = True, 10.0
            sim.script.watchdog_silent_s = 0.0
        time.sleep(0.3)
        assert sim.script.watchdog_trips == 0 and sim.script.program_running
        for _ in range(20):
            sim.advance(0.01)
        assert sim.script.watchdog_trips == 1 and not sim.script.program_running
    finally:
        sim.stop()


def test_an_external_clocks_catch_up_is_no_silence_after_an_update():
    """A world behind real time steps the time it owes at once; that time passed before an
    update applied meanwhile, and the watchdog must not count it after (a lab trial tripped
    at 141 ms of real silence in a 150 ms window). Silence counts on both clocks."""
    sim = URSimulator(URSimConfig(host="auto", motion_clock="external")).start()
    window_s = 0.5  # wide: the real-time steps below may run late on a busy machine
    try:
        with sim.lock:  # a running script with its watchdog, and an update just applied
            sim.script.program_running, sim.script.watchdog_hz = True, 1 / window_s
            sim.script.watchdog_silent_s, sim.script.watchdog_update_s = 0.0, now_s()
        updated = now_s()
        sim.advance(0.35)  # owed from before the update
        while now_s() - updated < 0.2:  # then in real time: 0.55 s of the world's clock
            time.sleep(0.01)
            sim.advance(0.01)
        assert sim.script.watchdog_trips == 0 and sim.script.program_running, (
            "a catch-up counted as silence"
        )
        while (
            sim.script.program_running and now_s() - updated < 5.0
        ):  # silent on both clocks: a stop
            time.sleep(0.01)
            sim.advance(0.01)
        assert sim.script.watchdog_trips == 1 and now_s() - updated > window_s
    finally:
        sim.stop()


@pytest.mark.slow
def test_raw_ur_rtde_servol_and_movej_against_the_simulator():
    """The calls URArm does not use, straight from ur-rtde: the simulator is general."""
    import rtde_control
    import rtde_receive

    with URSimProcess() as sim:
        clients = {
            "r": rtde_receive.RTDEReceiveInterface(sim.host),
            "c": rtde_control.RTDEControlInterface(sim.host),
        }
        try:
            _servol_then_movej(sim, **clients)
        finally:
            clients.clear()  # ur-rtde's destructors disconnect, before the simulator stops


def _servol_then_movej(sim: URSimProcess, r, c) -> None:
    start = np.array(r.getActualTCPPose())
    target = start.copy()
    for i in range(1, 26):  # 25 servo set-points, 2 mm apart, at 125 Hz
        target[0] = start[0] + 0.002 * i
        assert c.servoL(target.tolist(), 0.5, 0.5, 0.008, 0.1, 300)
        time.sleep(0.008)
    assert wait_until(lambda: abs(r.getActualTCPPose()[0] - target[0]) < 1e-4, 1.0)
    assert c.servoStop()
    q = np.array(r.getActualQ())
    q_target = q + np.array([0.05, -0.05, 0.05, 0.0, 0.0, 0.1])
    assert c.moveJ(q_target.tolist(), 1.0, 2.0)
    # the receive stream is a separate connection: its next packages show the end
    assert wait_until(lambda: np.allclose(r.getActualQ(), q_target, atol=1e-6), 1.0)
    c.stopScript()
    assert wait_until(lambda: not sim.stats()["program_running"], 1.0)
    assert {24, 16, 1, 255} <= set(sim.commands_seen())


class LaggingReceive:
    """ur-rtde's receive interface as a busy machine serves it: every value is from ``lag_s``
    ago (its thread behind), while the control connection already says the move ended."""

    def __init__(self, real, lag_s: float) -> None:
        import collections
        import threading

        self._real, self._lag_s = real, lag_s
        self._history: collections.deque = collections.deque(maxlen=2000)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()
        wait_until(lambda: len(self._history) > 0, 1.0)

    def _sample(self) -> None:
        while not self._stop.wait(0.001):
            r = self._real
            self._history.append(
                (time.monotonic(), r.getActualTCPPose(), r.getActualTCPSpeed(), r.getTimestamp())
            )

    def _then(self) -> tuple:
        """The newest sample from ``lag_s`` ago or before; where this process's sampling
        thread was starved across that moment (a busy machine), the first sample after it:
        the lag stays about ``lag_s``, not ``lag_s`` plus the starvation."""
        cutoff = time.monotonic() - self._lag_s
        history = list(self._history)
        older = [h for h in history if h[0] <= cutoff]
        if older and older[-1][0] >= cutoff - self._lag_s:
            return older[-1]
        newer = [h for h in history if h[0] > cutoff]
        return newer[0] if newer else history[-1]

    def getActualTCPPose(self):
        return self._then()[1]

    def getActualTCPSpeed(self):
        return self._then()[2]

    def getTimestamp(self):
        return self._then()[3]

    def __getattr__(self, name):
        return getattr(self._real, name)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1)


def test_move_to_returns_once_the_receive_stream_shows_the_arm_at_the_target(still_arm):
    """The control connection reports a move's end before a lagging receive stream shows it;
    the pose read right after move_to must be the target's, not one from the deceleration."""
    lagging = LaggingReceive(still_arm.receive.recv, lag_s=0.02)
    real, still_arm.receive.recv = still_arm.receive.recv, lagging
    try:
        target = still_arm.tcp_pose()
        target[:3] += [0.02, 0.0, 0.01]
        still_arm.move_to(target, speed=0.1)
        np.testing.assert_allclose(still_arm.tcp_pose()[:3], target[:3], atol=1e-5)
    finally:
        if still_arm.receive.recv is lagging:  # else move_to reconnected: a new interface, keep it
            still_arm.receive.recv = real
        lagging.close()
