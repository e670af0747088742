"""The tactile board: wire codec, stream parser, and the REAL driver against the
simulated board through pyserial on a pseudo-terminal."""

from __future__ import annotations

import os
import struct
import time
from collections.abc import Iterator

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from common.devices.lifecycle import build_device
from common.errors import (
    DeviceError,
    DeviceNotConnectedError,
    DeviceTimeoutError,
    ProtocolError,
    StaleDataError,
)
from common.tactile.synthetic import GeneratorParams
from robot_side.tactile import KINDS
from robot_side.tactile.board_calibration import (
    BoardCalibration,
    load_board_calibration,
    save_board_calibration,
)
from robot_side.tactile.board_sim import (
    SimulatedSerialTactileSensor,
    TactileBoardSimConfig,
    TactileBoardSimulator,
)
from robot_side.tactile.script import GraspScript, GraspStep
from robot_side.tactile.serial_board import SerialTactileConfig, SerialTactileSensor
from robot_side.tactile.wire import (
    PACKET_SIZE,
    StreamParser,
    crc16_ccitt,
    decode,
    encode,
)

# pty: the board streams through a pseudo-terminal, and the driver's reads have deadlines
pytestmark = [pytest.mark.timeout(30), pytest.mark.pty]

# -- the codec and the parser ----------------------------------------------------------

counts_st = st.lists(st.integers(0, 0xFFFF), min_size=100, max_size=100).map(
    lambda v: np.array(v, dtype=np.uint16).reshape(10, 10)
)


def test_crc_check_value() -> None:
    assert crc16_ccitt(b"123456789") == 0x29B1  # CRC-16/CCITT-FALSE's catalogue value


def test_packet_layout_is_what_the_doc_says() -> None:
    counts = np.arange(100, dtype=np.uint16).reshape(10, 10)
    p = encode(1, 0x01020304, counts)
    assert len(p) == PACKET_SIZE == 212
    assert p[:2] == b"\xa5\x5a" and p[2] == 1 and p[3] == 1
    assert p[4:8] == bytes([4, 3, 2, 1]) and p[8] == 10 and p[9] == 10
    assert p[10:12] == b"\x00\x00" and p[12:14] == b"\x01\x00"  # row 0, col 0 then col 1
    assert struct.unpack("<H", p[210:212])[0] == crc16_ccitt(p[2:210])


@pytest.mark.slow
@given(pad=st.integers(0, 1), seq=st.integers(0, 2**32 - 1), counts=counts_st)
def test_codec_round_trip(pad: int, seq: int, counts: np.ndarray) -> None:
    got = decode(encode(pad, seq, counts))
    assert got.pad == pad and got.seq == seq
    np.testing.assert_array_equal(got.counts, counts)


def test_decode_names_the_problem() -> None:
    p = bytearray(encode(0, 5, np.zeros((10, 10), np.uint16)))
    p[100] ^= 1
    with pytest.raises(ValueError, match="bad CRC"):
        decode(bytes(p))
    with pytest.raises(ValueError, match="212 bytes"):
        decode(bytes(p[:-1]))


def _packets(n: int, seed: int = 0) -> list[bytes]:
    rng = np.random.default_rng(seed)
    return [
        encode(k % 2, k // 2, rng.integers(0, 4096, (10, 10)).astype(np.uint16)) for k in range(n)
    ]


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    garbage=st.lists(st.binary(max_size=300), min_size=9, max_size=9),
    chunk=st.integers(1, 700),
)
def test_parser_finds_every_good_packet_among_garbage(garbage: list[bytes], chunk: int) -> None:
    packets = _packets(8)
    stream = b"".join(g + p for g, p in zip(garbage, [*packets, b""], strict=True))
    parser = StreamParser()
    got = []
    for i in range(0, len(stream), chunk):
        got += parser.feed(stream[i : i + chunk])
    assert [(p.pad, p.seq) for p in got] == [(k % 2, k // 2) for k in range(8)]
    s = parser.stats
    assert s.packets == 8
    assert s.dropped_bytes == sum(map(len, garbage)) - len(parser._buf)


@settings(max_examples=60, deadline=None)
@given(data=st.binary(max_size=3000), chunk=st.integers(1, 500))
def test_parser_survives_pure_garbage(data: bytes, chunk: int) -> None:
    parser = StreamParser()
    for i in range(0, len(data), chunk):
        assert parser.feed(data[i : i + chunk]) == []
        assert len(parser._buf) < PACKET_SIZE  # bounded, whatever arrives


def test_bad_crc_does_not_cost_the_next_packet() -> None:
    a, b, c = _packets(3)
    bad = bytearray(a)
    bad[50] ^= 0x40
    parser = StreamParser()
    got = parser.feed(bytes(bad) + b + c)
    assert [(p.pad, p.seq) for p in got] == [(1, 0), (0, 1)]
    assert parser.stats.bad_crc == 1 and parser.stats.dropped_bytes == PACKET_SIZE


def test_truncated_packet_followed_at_once_by_a_good_one() -> None:
    a, b = _packets(2)
    parser = StreamParser()
    got = parser.feed(a[:100] + a[117:] + b)  # 17 bytes lost inside packet a
    assert [(p.pad, p.seq) for p in got] == [(1, 0)]
    assert parser.stats.dropped_bytes == PACKET_SIZE - 17


def test_parse_cost_per_packet_is_small() -> None:
    stream = b"".join(_packets(600))
    parser = StreamParser()
    t = time.perf_counter()
    for i in range(0, len(stream), 512):
        parser.feed(stream[i : i + 512])
    per_packet_us = (time.perf_counter() - t) / 600 * 1e6
    assert parser.stats.packets == 600
    assert per_packet_us < 200, per_packet_us  # measured ~4-5 us; 240 packets/s


# -- the driver against the simulated board ----------------------------------------------


def _script(delay_s: float = 0.6) -> GraspScript:
    return GraspScript(
        grasps=[
            GraspStep(pattern=4, grip_level=25, ramp_s=0.05, hold_s=5.0, release_s=0.0, pause_s=0.1)
        ],
        start_delay_s=delay_s,
    )


def _board(**kw: object) -> TactileBoardSimConfig:
    kw.setdefault("script", _script())
    return TactileBoardSimConfig(**kw)  # type: ignore[arg-type]


@pytest.fixture
def board() -> Iterator[TactileBoardSimulator]:
    with TactileBoardSimulator(_board()) as sim:
        yield sim


def _driver(port: str, **kw: object) -> SerialTactileSensor:
    kw.setdefault("connect_timeout_s", 1.0)
    kw.setdefault("reconnect_interval_s", 0.05)
    return SerialTactileSensor(SerialTactileConfig(port=port, **kw))  # type: ignore[arg-type]


def _frames(sensor: SerialTactileSensor, n: int) -> list:
    out = []
    sample = sensor.latest()
    after = sample.seq if sample else 0
    for _ in range(n):
        sample = sensor.wait_for_frame(after, 1.0)
        assert sample is not None, sensor.status()
        out.append(sample)
        after = sample.seq
    return out


def _wait(cond, timeout_s: float = 2.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, "condition not met in time"
        time.sleep(0.005)


def _wait_for_pattern(board, sensor, pattern: int) -> None:
    """Until the newest frame shows the board's ``pattern``: what the frames hold, not how
    fresh they are (the staleness rule has tests of its own; a loaded test process may
    hold the simulator's thread back for longer than a frame)."""

    def shown() -> bool:
        sample = sensor.latest()
        if sample is None:
            return False
        truth = board.truth_for(sample.seq - 1)
        return truth is not None and truth.pattern == pattern

    _wait(shown)


def _assert_same_newtons(driver_frame: np.ndarray, sim_frame: np.ndarray) -> None:
    """Equal up to ADC quantisation and noise, allowing taxels right at the 1 N floor."""
    diff = np.abs(driver_frame - sim_frame)
    at_floor = (np.minimum(driver_frame, sim_frame) == 0) & (
        np.maximum(driver_frame, sim_frame) < 1.05
    )
    assert np.all((diff < 0.03) | at_floor), float(diff[~at_floor].max())


@pytest.mark.slow
def test_calibration_and_mirroring_reproduce_the_boards_newtons(board) -> None:
    with _driver(board.port) as sensor:
        sensor.set_calibration(board.calibration)
        _wait_for_pattern(board, sensor, 4)
        compared = 0
        for sample in _frames(sensor, 10):
            sim_frame = board.frame_for(sample.seq - 1)
            if sim_frame is None or sample.seq - 1 < 2:
                continue
            assert sample.frame.dtype == np.float32 and sample.frame.shape == (2, 10, 10)
            _assert_same_newtons(sample.frame, sim_frame)
            compared += 1
            # The 45-degree band is not left-right symmetric, so an unmirrored
            # finger 2 would be told apart here.
            assert np.abs(sample.frame[1] - sim_frame[1][:, ::-1]).max() > 1.0
        assert compared >= 8
        assert sample.frame.max() > 1.0 and sample.frame.max() <= 9.0
        nz = sample.frame[sample.frame > 0]
        assert nz.min() >= 1.0  # the floor


@pytest.mark.slow
def test_without_mirroring_finger2_comes_out_in_its_own_view(board) -> None:
    with _driver(board.port, mirror_finger2=False) as sensor:
        sensor.set_calibration(board.calibration)
        _wait_for_pattern(board, sensor, 4)
        sample = _frames(sensor, 1)[0]
        sim_frame = board.frame_for(sample.seq - 1)
        _assert_same_newtons(sample.frame[1], sim_frame[1][:, ::-1])


@settings(max_examples=60, deadline=None)
@given(
    counts=st.lists(st.integers(0, 0xFFFF), min_size=200, max_size=200),
    zero=st.floats(0, 4000),
    gain=st.floats(1e-4, 0.1),
    mirror=st.booleans(),
    floor=st.floats(0, 2),
    saturation=st.floats(2.5, 20),
)
@pytest.mark.slow
def test_compiled_conversion_is_bit_identical_to_numpy(
    counts: list[int], zero: float, gain: float, mirror: bool, floor: float, saturation: float
) -> None:
    pytest.importorskip("numba")
    from robot_side.tactile.serial_board import ScanConverter

    rng = np.random.default_rng(len(counts) + int(zero))
    cal = BoardCalibration(
        zero + rng.uniform(-50, 50, (2, 10, 10)), gain * rng.uniform(0.5, 2, (2, 10, 10))
    )
    cfg = SerialTactileConfig(mirror_finger2=mirror, floor_n=floor, saturation_n=saturation)
    converter = ScanConverter(cal, cfg)
    assert converter._compiled is not None
    payloads = np.array(counts, "<u2").tobytes()
    compiled, reference = converter(payloads), converter.numpy_path(payloads)
    assert compiled.dtype == np.float32 and compiled.shape == (2, 10, 10)
    np.testing.assert_array_equal(compiled, reference)
    with pytest.raises(ValueError, match="400 count bytes"):
        converter(payloads[:-2])


def test_capture_zero_recovers_the_boards_offsets() -> None:
    gen = GeneratorParams(stuck_taxel_fraction=0.0)  # a stuck taxel is zeroed away, by design
    # no contact before the zero is captured, however long a busy machine takes to connect:
    # the grasp starts long after this test has ended
    with TactileBoardSimulator(_board(generator=gen, script=_script(delay_s=600.0))) as board:
        with _driver(board.port) as sensor:
            wrong = BoardCalibration(
                np.full((2, 10, 10), 300.0), board.calibration.gain_n_per_count
            )
            sensor.set_calibration(wrong)
            zero = sensor.capture_zero(24)
        np.testing.assert_allclose(zero, board.calibration.zero_counts, atol=1.5)


def test_calibration_file_round_trip_and_use(board, tmp_path) -> None:
    path = tmp_path / "tactile.toml"
    save_board_calibration(board.calibration, path)
    loaded = load_board_calibration(path)
    np.testing.assert_allclose(loaded.zero_counts, board.calibration.zero_counts, atol=0.01)
    np.testing.assert_allclose(
        loaded.gain_n_per_count, board.calibration.gain_n_per_count, rtol=1e-5
    )
    with _driver(board.port, calibration_file=path) as sensor:
        _wait_for_pattern(board, sensor, 4)
        sample = _frames(sensor, 1)[0]
        _assert_same_newtons(sample.frame, board.frame_for(sample.seq - 1))


def _settle(board: TactileBoardSimulator, sensor: SerialTactileSensor) -> tuple[int, dict]:
    """Pause the board and let the driver catch up: then seq and counters agree."""
    board.pause()
    time.sleep(0.04)
    return sensor.latest().seq, sensor.stats()


def _around_fault(board, sensor, fault) -> tuple[int, dict, dict]:
    """(published seqs spanned, counters before, counters after) around one fault.

    The board is paused while the fault is armed and while the counters are
    read, so the test does not depend on keeping up with 120 Hz.
    """
    _frames(sensor, 2)
    prev, before = _settle(board, sensor)
    fault()
    board.resume()
    _frames(sensor, 4)
    last, after = _settle(board, sensor)
    board.resume()
    return last - prev, before, after


def _delta(before: dict, after: dict, key: str) -> int:
    return after[key] - before[key]


def test_garbage_on_the_line_costs_no_frame(board) -> None:
    with _driver(board.port) as sensor:
        span, before, after = _around_fault(board, sensor, lambda: board.inject_garbage(700))
        assert _delta(before, after, "dropped_bytes") >= 700
        assert _delta(before, after, "resyncs") >= 1
        assert _delta(before, after, "seq_gaps") == 0
        assert _delta(before, after, "incomplete_frames") == 0
        assert span == _delta(before, after, "frames")  # every scan arrived


def test_bad_crc_loses_only_its_own_scan(board) -> None:
    with _driver(board.port) as sensor:
        span, before, after = _around_fault(board, sensor, lambda: board.corrupt_next(1))
        assert _delta(before, after, "bad_crc") == 1
        assert _delta(before, after, "seq_gaps") == 1
        # Pad 1 of the damaged scan still parsed: that is what "incomplete" counts.
        assert _delta(before, after, "incomplete_frames") == 1
        assert span == _delta(before, after, "frames") + 1  # only the damaged scan is missing


def test_dropped_bytes_lose_only_their_own_scan(board) -> None:
    with _driver(board.port) as sensor:
        span, before, after = _around_fault(board, sensor, lambda: board.drop_bytes_next(17))
        assert _delta(before, after, "bad_crc") >= 1
        assert _delta(before, after, "seq_gaps") == 1
        assert _delta(before, after, "incomplete_frames") == 1
        assert span == _delta(before, after, "frames") + 1


def test_lost_scans_show_as_sequence_gaps(board) -> None:
    with _driver(board.port) as sensor:
        span, before, after = _around_fault(board, sensor, lambda: board.skip_scans(5))
        assert _delta(before, after, "seq_gaps") == 5
        assert span == _delta(before, after, "frames") + 5  # the published seq keeps the gap


def test_sequence_wraps_without_going_back() -> None:
    # the wrap 3 s of scans after the board's start: a busy machine once opened the driver
    # 1.35 s after it, past a wrap 10 scans in, and the test saw no wrap at all
    with (
        TactileBoardSimulator(_board(first_seq=2**32 - 360)) as board,
        _driver(board.port) as sensor,
    ):
        first = _frames(sensor, 1)[0].seq
        assert first < 2**32, f"the driver's first frame came after the wrap ({first})"
        seqs = [first]
        while seqs[-1] < 2**32 + 10:
            seqs += [s.seq for s in _frames(sensor, 10)]
        assert seqs == sorted(set(seqs))
        assert seqs[-1] > 2**32  # unwrapped
        assert sensor.stats()["board_restarts"] == 0
        assert sensor.stats()["seq_gaps"] == 0


def test_a_board_that_stops_streaming_is_a_stale_data_error(board) -> None:
    with _driver(board.port) as sensor:
        _frames(sensor, 2)
        board.pause()
        time.sleep(0.08)
        with pytest.raises(StaleDataError, match="stopped streaming"):
            sensor.read_latest(max_age_ms=40)
        board.resume()
        _frames(sensor, 2)
        assert sensor.read_latest(max_age_ms=40).frame.shape == (2, 10, 10)


def test_vanished_board_is_detected_and_reconnected(board) -> None:
    with _driver(board.port) as sensor:
        _frames(sensor, 2)  # streaming
        board.unplug()
        _wait(lambda: sensor.stats()["disconnects"] == 1)
        assert sensor.status()["link"] == "down"
        time.sleep(0.03)  # let the newest frame age past the limit
        with pytest.raises(StaleDataError, match="vanished"):
            sensor.read_latest(max_age_ms=20)
        time.sleep(0.1)  # a few failed reopen attempts while unplugged
        # frames the board sent before the unplug (a loaded test thread reached it late) are
        # not the reconnect's: the one asked for is newer than the newest of them
        before = sensor.latest()
        board.replug()
        _wait(lambda: sensor.stats()["reconnects"] == 1, timeout_s=5.0)
        again = sensor.wait_for_frame(before.seq, 2.0)
        assert again is not None and again.seq > before.seq
        assert sensor.status()["link"] == "open"


def test_explicit_reconnect_without_auto_reconnect(board) -> None:
    sensor = _driver(board.port, auto_reconnect=False)
    with sensor:
        first = _frames(sensor, 1)[0]
        board.unplug()
        _wait(lambda: sensor.stats()["disconnects"] == 1)
        board.replug()
        time.sleep(0.1)
        with pytest.raises(StaleDataError, match="auto_reconnect is off"):
            sensor.read_latest(max_age_ms=20)
        sensor.reconnect()
        assert sensor.wait_for_frame(first.seq, 1.0) is not None


def test_missing_port_is_named_with_a_hint() -> None:
    sensor = _driver("/dev/serial/by-id/usb-no-such-board")
    with pytest.raises(DeviceError, match=r"usb-no-such-board.*ls -l /dev/serial/by-id"):
        sensor.connect()
    assert not sensor.is_connected
    with pytest.raises(DeviceNotConnectedError):
        sensor.read_latest()


def test_wrong_baud_rate_is_called_that(board) -> None:
    sensor = _driver(board.port, baudrate=115200, connect_timeout_s=0.3)
    with pytest.raises(ProtocolError, match="wrong baud rate"):
        sensor.connect()
    assert not sensor.is_connected


def test_silent_board_times_out_at_connect() -> None:
    master, slave = os.openpty()
    try:
        sensor = _driver(os.ttyname(slave), connect_timeout_s=0.2)
        with pytest.raises(DeviceTimeoutError, match="sent nothing"):
            sensor.connect()
    finally:
        os.close(master)
        os.close(slave)


def test_simulated_serial_kind_attaches_ground_truth() -> None:
    section = {
        "kind": "simulated_serial",
        "board": {
            "seed": 3,
            "script": {
                "start_delay_s": 0.0,
                "grasps": [{"pattern": 7, "grip_level": 15, "ramp_s": 0.0, "hold_s": 5.0}],
            },
        },
        "driver": {"max_age_ms": 100.0},
    }
    sensor = build_device(KINDS, section, "tactile")
    assert isinstance(sensor, SimulatedSerialTactileSensor)
    with sensor:
        samples = _frames(sensor, 3)
        for s in samples:
            assert s.truth is not None and s.truth.pattern == 7
            assert s.truth == sensor.simulator.truth_for(s.seq - 1)
            _assert_same_newtons(s.frame, sensor.simulator.frame_for(s.seq - 1))
        assert sensor.read_latest().seq >= samples[-1].seq
        assert sensor.status()["simulator"]["scans"] > 0
    assert not sensor.simulator.running
