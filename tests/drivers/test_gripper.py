"""The real Robotiq drivers against the simulators: URCap socket over loopback TCP,
Modbus RTU over a pseudo-terminal. Each test gets its own simulator on its own
loopback address and a free port, so tests can run side by side."""

from __future__ import annotations

import itertools
import socket
import struct
import time

import pytest
from hypothesis import given
from hypothesis import strategies as st

from common.config.typed import from_dict
from common.devices.lifecycle import build_device
from common.errors import (
    ConfigError,
    DeviceNotConnectedError,
    DeviceTimeoutError,
    ProtocolError,
)
from robot_side.gripper import KINDS
from robot_side.gripper.base import N_GRIP_LEVELS, GripLevels, GripperFaultError
from robot_side.gripper.modbus_rtu import (
    RobotiqRtuConfig,
    RobotiqRtuGripper,
    crc16,
    read_request,
    write_request,
)
from robot_side.gripper.rtu_sim import RtuGripperSim
from robot_side.gripper.sim import (
    GripperModelConfig,
    GripperSimConfig,
    GripperSimServer,
    SimulatedGripper,
    SimulatedGripperConfig,
)
from robot_side.gripper.urcap_socket import RobotiqSocketConfig, RobotiqSocketGripper

pytestmark = pytest.mark.timeout(20)
#: the Modbus RTU tests: the simulator answers through a pseudo-terminal within reply windows
pty = pytest.mark.pty

_hosts = itertools.cycle(range(2, 250))
FAST = dict(activation_time_s=0.05, min_speed_counts_s=500.0, max_speed_counts_s=4000.0)
LEVELS = GripLevels(speed=255)


def loopback() -> str:
    return f"127.0.1.{next(_hosts)}"


def wait_until(cond, timeout_s: float = 2.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(0.005)
    return cond()


def settled(gripper) -> bool:
    return gripper.state().object_status != 0


@pytest.fixture
def server():
    s = GripperSimServer(GripperSimConfig(host=loopback(), model=GripperModelConfig(**FAST)))
    s.start()
    yield s
    s.stop()


@pytest.fixture
def gripper(server):
    g = RobotiqSocketGripper(
        RobotiqSocketConfig(host=server.host, port=server.port, reply_timeout_s=0.3, levels=LEVELS)
    )
    g.connect()
    yield g
    g.disconnect()  # before the server stops


# -- grip levels (pure) -------------------------------------------------------


def test_levels_span_lightest_touch_to_strongest_squeeze():
    lv = GripLevels()
    positions = [lv.position(n) for n in range(1, N_GRIP_LEVELS + 1)]
    forces = [lv.force(n) for n in range(1, N_GRIP_LEVELS + 1)]
    assert positions[0] == lv.level1_position and positions[-1] == lv.level31_position
    assert all(b > a for a, b in itertools.pairwise(positions))  # distinct
    assert all(b >= a for a, b in itertools.pairwise(forces))
    assert [lv.level_at(p) for p in positions] == list(range(1, N_GRIP_LEVELS + 1))
    assert lv.level_at(0) is None  # open


@given(level=st.integers(1, N_GRIP_LEVELS))
def test_every_level_reads_back_as_itself(level):
    lv = GripLevels(level1_position=150, level31_position=240)
    assert lv.level_at(lv.position(level)) == level


def test_levels_config_refuses_overlapping_levels():
    with pytest.raises(ConfigError, match="at least 30 counts"):
        from_dict(GripLevels, {"level1_position": 200, "level31_position": 220})


# -- URCap socket driver against the socket simulator -------------------------


def test_activation_runs_the_sta_sequence(server):
    g = RobotiqSocketGripper(
        RobotiqSocketConfig(host=server.host, port=server.port, activate_on_connect=False)
    )
    g.connect()
    try:
        assert g.state().activation == 0
        g.activate()
        assert g.is_active() and g.position() == 0
        g.activate()  # already active: left alone
    finally:
        g.disconnect()


HELD = ("ACT", "GTO", "STA", "PRE", "SPE", "FOR")


def _registers(model) -> dict[str, int]:
    return {k: v for k, v in model.read().items() if k in (*HELD, "POS", "OBJ")}


def _holds_through_a_restart(model, connect_again) -> None:
    """A node holding the pipette dies; a new one connects: the fingers must not move."""
    held = _registers(model)
    assert held["ACT"] == 1 and held["STA"] == 3 and held["PRE"] > 0 and held["OBJ"] in (2, 3)
    again = connect_again()  # activate_on_connect, as the node's drivers do
    try:
        assert again.grip_level() is not None
        time.sleep(0.3)  # the fingers would be on their way open by now
        assert _registers(model) == held, "connecting to an active gripper moved it"
    finally:
        again.disconnect()


def test_a_new_socket_driver_leaves_a_closed_gripper_closed(server):
    def driver() -> RobotiqSocketGripper:
        g = RobotiqSocketGripper(
            RobotiqSocketConfig(host=server.host, port=server.port, levels=LEVELS)
        )
        g.connect()
        return g

    first = driver()
    first.close_to_level(20)
    assert wait_until(lambda: settled(first))
    first._sock.close()  # the process dies: no goodbye, no last command
    lines: list[str] = []
    handle = server.handle
    server.handle = lambda line: (lines.append(line), handle(line))[1]
    _holds_through_a_restart(server.model, driver)
    assert not [line for line in lines if line.startswith("SET")], lines


@pty
def test_a_new_rtu_driver_leaves_a_closed_gripper_closed(rtu):
    sim, first = rtu
    first.connect()
    first.close_to_level(20)
    assert wait_until(lambda: settled(first))
    first.disconnect()

    def driver() -> RobotiqRtuGripper:
        g = RobotiqRtuGripper(RobotiqRtuConfig(port=sim.port, reply_timeout_s=0.25, retries=2))
        g.connect()
        return g

    _holds_through_a_restart(sim.model, driver)


def test_moving_before_activation_reports_the_fault(server):
    g = RobotiqSocketGripper(
        RobotiqSocketConfig(host=server.host, port=server.port, activate_on_connect=False)
    )
    g.connect()
    try:
        g.move(100)
        assert g.fault() == 0x07
        assert "activate" in g.status()["fault_text"]
    finally:
        g.disconnect()


def test_move_is_non_blocking_and_fingers_travel_at_finite_speed():
    slow = GripperModelConfig(activation_time_s=0.05, min_speed_counts_s=200.0)
    with GripperSimServer(GripperSimConfig(host=loopback(), model=slow)) as server:
        g = RobotiqSocketGripper(RobotiqSocketConfig(host=server.host, port=server.port))
        with g:
            t0 = time.monotonic()
            g.move(100, speed=0, force=255)  # SPE 0: 200 counts/s here, 0.5 s of travel
            assert time.monotonic() - t0 < 0.25  # returned long before the fingers arrive
            assert g.state().object_status == 0  # still moving
            assert 0 <= g.position() < 100
            assert wait_until(lambda: settled(g), 2.0)
            assert time.monotonic() - t0 >= 0.45
            assert g.position() == 100


def test_rigid_object_stops_the_fingers_and_is_detected(server, gripper):
    server.model.set_object(True, contact_position=180, compression_at_full_force=0.0)
    gripper.move(255)
    assert wait_until(lambda: settled(gripper))
    assert gripper.object_detected()
    assert gripper.state().object_status == 2
    assert gripper.position() == 180
    gripper.open()
    assert wait_until(lambda: settled(gripper) and gripper.position() == 0)
    assert not gripper.object_detected()


def test_without_an_object_the_fingers_reach_the_request(server, gripper):
    server.model.set_object(False)
    gripper.move(140)
    assert wait_until(lambda: settled(gripper))
    assert gripper.state().object_status == 3 and gripper.position() == 140
    assert not gripper.object_detected()
    assert gripper.grip_level() is None  # open of level 1
    gripper.move(255)
    assert wait_until(lambda: settled(gripper))
    assert gripper.grip_level() is None  # closed on nothing


def test_close_to_level_reads_back_the_level_on_a_soft_pipette(gripper):
    for level in (1, 12, 31):
        gripper.close_to_level(level)
        assert wait_until(lambda: settled(gripper))
        assert gripper.grip_level() == level
        assert gripper.state().requested_position == LEVELS.position(level)
    gripper.open()
    assert wait_until(lambda: gripper.grip_level() is None)


def test_an_ease_lets_go_of_a_held_pipette_without_opening_the_stroke_and_never_closes(
    server, gripper
):
    """The assist's re-grasp: just past level 1, so closing back is a few counts, not 200."""
    gripper.close_to_level(16)
    assert wait_until(lambda: settled(gripper)) and gripper.grip_level() == 16
    gripper.ease()
    assert wait_until(lambda: gripper.state().object_status == 3)  # at its request
    assert gripper.position() == LEVELS.ease_position() < LEVELS.level1_position
    assert gripper.grip_level() is None  # reads open: nothing held
    assert gripper.position() > 150  # not the whole stroke
    gripper.open()
    assert wait_until(lambda: gripper.position() == 0)
    gripper.ease()  # already more open: stays put
    assert gripper.state().requested_position == 0
    time.sleep(0.1)
    assert gripper.position() == 0


def test_a_stiffer_pipette_stops_a_strong_level_early(server, gripper):
    server.model.set_object(True, contact_position=196, compression_at_full_force=20.0)
    gripper.close_to_level(31)
    assert wait_until(lambda: settled(gripper))
    assert gripper.object_detected()
    level = gripper.grip_level()
    assert level is not None and level < 31  # what the fingers really squeeze


def test_hold_stops_the_fingers_where_they_are(server, gripper):
    server.model.set_object(False)
    gripper.move(255, speed=0)
    assert wait_until(lambda: gripper.position() > 40)
    gripper.hold()
    held = gripper.position()
    time.sleep(0.1)
    assert abs(gripper.position() - held) <= 3
    assert gripper.state().requested_position == pytest.approx(held, abs=3)


def test_values_are_clamped_and_nonsense_refused(gripper):
    gripper.move(400, speed=999, force=-5)
    assert gripper.state().requested_position == 255
    with pytest.raises(ValueError, match=r"0\.\.255"):
        gripper.move(float("nan"))
    with pytest.raises(ValueError, match=r"not in 1\.\.31"):
        gripper.close_to_level(32)
    with pytest.raises(ValueError, match="integer"):
        gripper.close_to_level(2.5)


def test_a_fault_is_reported_with_what_to_do(server, gripper):
    server.model.inject_fault(0x0E)
    assert gripper.fault() == 0x0E
    assert "overcurrent" in gripper.status()["fault_text"]


def test_activation_fault_raises(server):
    g = RobotiqSocketGripper(
        RobotiqSocketConfig(host=server.host, port=server.port, activate_on_connect=False)
    )
    g.connect()
    try:
        server.model.fail_next_activation(0x0D)
        with pytest.raises(GripperFaultError, match="activation fault"):
            g.activate()
    finally:
        g.disconnect()


def test_vanished_gripper_is_a_clear_error_and_reconnecting_works(server, gripper):
    server.drop_connections()
    t0 = time.monotonic()
    with pytest.raises(DeviceNotConnectedError, match="connection lost"):
        gripper.position()
    assert time.monotonic() - t0 < 2.0
    assert not gripper.is_connected
    with pytest.raises(DeviceNotConnectedError, match="call connect"):
        gripper.open()
    gripper.connect()  # the URCap is back
    assert gripper.is_active()


def test_a_hung_urcap_times_out_instead_of_hanging(server, gripper):
    server.mute()
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeoutError, match="did not answer"):
        gripper.position()
    assert time.monotonic() - t0 < 2.0  # the 0.3 s deadline, not a hang
    assert not gripper.is_connected  # a late reply can never be taken for the next one
    server.mute(False)
    gripper.connect()
    assert gripper.position() == 0


def test_stopped_server_refuses_connections_clearly():
    server = GripperSimServer(GripperSimConfig(host=loopback())).start()
    host, port = server.host, server.port
    server.stop()
    g = RobotiqSocketGripper(RobotiqSocketConfig(host=host, port=port, connect_timeout_s=0.5))
    with pytest.raises(DeviceNotConnectedError, match="cannot reach the Robotiq URCap"):
        g.connect()


def test_a_wrong_reply_is_a_protocol_error():
    """Something that is not the URCap listens on the port."""
    listener = socket.create_server((loopback(), 0))
    host, port = listener.getsockname()[:2]
    g = RobotiqSocketGripper(
        RobotiqSocketConfig(host=host, port=port, activate_on_connect=False, reply_timeout_s=1)
    )
    g.connect()
    peer, _ = listener.accept()
    try:
        peer.sendall(b"HTTP/1.1 400 Bad Request\n")
        with pytest.raises(ProtocolError, match="Robotiq URCap"):
            g.position()
        assert not g.is_connected
    finally:
        peer.close()
        listener.close()


def test_simulator_speaks_the_urcap_protocol(server):
    with socket.create_connection((server.host, server.port), timeout=1) as s:
        f = s.makefile("rwb")
        for line, expect in (
            (b"GET STA", b"STA 0"),
            (b"SET ACT 1", b"ack"),
            (b"SET POS 10 SPE 255 FOR 100 GTO 1", b"ack"),
            (b"GET PRE", b"PRE 10"),
            (b"GET NOPE", b"?"),
        ):
            f.write(line + b"\n")
            f.flush()
            assert f.readline().strip() == expect


def test_socket_round_trip_is_fast(gripper):
    n = 200
    t0 = time.perf_counter()
    for _ in range(n):
        gripper.position()
    per_call = (time.perf_counter() - t0) / n
    assert per_call < 0.005, f"{per_call * 1e6:.0f} us per GET"


# -- the "simulated" kind ------------------------------------------------------


def test_simulated_kind_is_the_socket_driver_on_an_in_process_simulator():
    g = build_device(
        KINDS,
        {"kind": "simulated", "host": loopback(), "sim": FAST, "levels": {"speed": 255}},
        "gripper",
    )
    assert isinstance(g, SimulatedGripper) and isinstance(g, RobotiqSocketGripper)
    with g:
        assert g.server is not None and g.config.port == g.server.port
        g.close_to_level(5)
        assert wait_until(lambda: settled(g))
        assert g.grip_level() == 5
    assert g.server is None and not g.is_connected
    with g:  # connects again on a fresh simulator
        assert g.is_active()


def test_simulated_config_rejects_unknown_keys():
    with pytest.raises(ConfigError, match="unknown key"):
        from_dict(SimulatedGripperConfig, {"sim": {"stiffness": 3}})


# -- Modbus RTU driver against the pty simulator ------------------------------


def test_crc_matches_the_manual_example():
    # Robotiq 2F manual: "09 03 07 D0 00 01 85 CF" reads the first status register
    assert read_request(9, 0x07D0, 1, function=3).hex(" ") == "09 03 07 d0 00 01 85 cf"
    assert crc16(b"123456789") == 0x4B37  # CRC-16/Modbus check value
    frame = write_request(9, 0x03E8, bytes([0x09, 0, 0, 0xFF, 0xFF, 0xFF]))
    assert frame[:7].hex(" ") == "09 10 03 e8 00 03 06"


@pytest.fixture
def rtu():
    sim = RtuGripperSim(GripperModelConfig(**FAST)).start()
    # generous deadlines: the pty and both threads share two cores with other tests (a lane's
    # machine once held the simulator's replies past three windows of 0.25 s)
    g = RobotiqRtuGripper(
        RobotiqRtuConfig(port=sim.port, reply_timeout_s=0.25, retries=4, levels=LEVELS)
    )
    yield sim, g
    g.disconnect()
    sim.stop()


@pty
def test_rtu_activates_moves_and_detects_an_object(rtu):
    sim, g = rtu
    g.connect()
    assert g.is_active()
    sim.model.set_object(True, contact_position=170, compression_at_full_force=0.0)
    g.move(255)
    assert wait_until(lambda: settled(g))
    assert g.object_detected() and g.position() == 170
    g.close_to_level(1)
    assert wait_until(lambda: settled(g))
    g.open()
    assert wait_until(lambda: g.position() == 0)


@pty
def test_rtu_grip_levels(rtu):
    _, g = rtu
    g.connect()
    g.close_to_level(20)
    assert wait_until(lambda: settled(g))
    assert g.grip_level() == 20


@pty
def test_rtu_retries_a_corrupt_reply_and_counts_it(rtu):
    sim, g = rtu
    g.connect()
    sim.corrupt_next = 1
    assert g.position() == 0
    assert g.status()["crc_errors"] == 1


@pty
def test_rtu_gives_up_with_a_clear_error_when_the_gripper_is_silent(rtu):
    sim, g = rtu
    g.connect()
    sim.muted = True
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeoutError, match="no reply after 5 tries"):
        g.position()
    assert time.monotonic() - t0 < 3.0  # 3 x 0.25 s, with slack for a loaded machine
    sim.muted = False
    assert g.position() == 0  # the line recovers without reconnecting


@pty
def test_rtu_skips_garbage_on_the_line(rtu):
    sim, g = rtu
    g.connect()
    g._serial.write(b"\x00\xff\x09\x10garbage")  # noise before the next request
    assert g.position() == 0
    assert sim.crc_errors > 0


@pty
def test_rtu_wrong_slave_id_times_out(rtu):
    sim, _ = rtu
    g = RobotiqRtuGripper(RobotiqRtuConfig(port=sim.port, slave_id=3, reply_timeout_s=0.1))
    with pytest.raises(DeviceTimeoutError, match="slave 3"):
        g.connect()
    assert not g.is_connected


def test_rtu_missing_port_is_a_clear_error():
    g = RobotiqRtuGripper(RobotiqRtuConfig(port="/dev/does-not-exist"))
    with pytest.raises(DeviceNotConnectedError, match="cannot open /dev/does-not-exist"):
        g.connect()


@pty
def test_rtu_simulator_answers_exceptions_for_wrong_addresses(rtu):
    _, g = rtu
    g.connect()
    g._serial.write(read_request(9, 0x1234, 3))
    reply, deadline = b"", time.monotonic() + 2.0  # the reply's format, not its timing
    while len(reply) < 5 and time.monotonic() < deadline:
        reply += g._serial.read(5 - len(reply))
    assert reply[:3] == bytes([9, 0x84, 2])
    assert struct.unpack("<H", reply[3:])[0] == crc16(reply[:3])
