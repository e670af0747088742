"""The recorder: what goes in comes back, from any thread, also from a file cut short."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from common.recording.mcap_recorder import (
    McapRecorder,
    RecordingError,
    RecordingReader,
    read_metadata,
    read_recording,
    recover_recording,
)
from common.wire.codec import encode
from common.wire.messages import Stimulus

HERE = Path(__file__).parent


def _stimulus_wire(seq: int) -> bytes:
    stim = np.zeros((3, 3), np.float32)
    stim[seq % 3, 1] = 2.5
    return encode(
        Stimulus(
            seq=seq,
            t_send_ns=10,
            t_capture_ns=9,
            frame_seq=seq,
            mode="direct",
            contact=True,
            stimulus=stim,
        )
    )


def test_every_value_type_round_trips(tmp_path):
    path = tmp_path / "r.mcap"
    frame = np.linspace(0, 9, 200, dtype=np.float32).reshape(2, 10, 10)
    records = [
        ("robot/frame", 5, {"frame": frame, "frame_seq": 1, "t_capture_ns": 2**62}),
        ("robot/stimulus", 6, {"seq": 1, "wire": _stimulus_wire(1)}),
        (
            "operator/servo_goals",
            7,
            {
                "ids": np.arange(1, 7, dtype=np.int64),
                "counts": np.array([2048, 2000, 1990, 2100, 3000, 1500]),
                "angles": np.linspace(-1, 1, 6).reshape(3, 2),
            },
        ),
        ("robot/command", 8, {"action": "arm_jog", "velocity": [0.1, 0, 0, 0, 0, 0.2], "x": None}),
        ("operator/link", 9, {"state": "ok", "ok": True, "rate": 1.5, "n": 3}),
        ("custom/channel", 10, {"blob": b"\x00\xff", "nested": {"a": np.ones(2, np.float32)}}),
    ]
    with McapRecorder(path, metadata={"deepxpalm.node": {"node": "robot"}}) as rec:
        for channel, t, record in records:
            rec.write(channel, t, record)
    got = list(read_recording(path))
    assert [(c, t) for c, t, _ in got] == [(c, t) for c, t, _ in records]
    for (_, _, want), (_, _, have) in zip(records, got, strict=True):
        for key, value in want.items():
            if isinstance(value, np.ndarray):
                assert have[key].dtype == value.dtype and np.array_equal(have[key], value)
            elif isinstance(value, dict):
                assert np.array_equal(have[key]["a"], value["a"])
                assert have[key]["a"].dtype == np.float32
            else:
                assert have[key] == value, key
    decoded = got[1][2]["decoded"]
    assert decoded["type"] == "stimulus" and decoded["stimulus"].dtype == np.float32
    assert read_metadata(path)["deepxpalm.node"] == {"node": "robot"}
    assert "wall_offset_ns" in read_metadata(path)["deepxpalm.clock"]


def test_a_type_change_after_the_first_record_is_still_restored(tmp_path):
    path = tmp_path / "r.mcap"
    with McapRecorder(path) as rec:
        rec.write("robot/command", 1, {"velocity": None})
        rec.write("robot/command", 2, {"velocity": np.ones(6, np.float32)})
    got = [r for _, _, r in read_recording(path)]
    assert got[0]["velocity"] is None
    assert got[1]["velocity"].dtype == np.float32


def test_non_finite_values_are_written_as_null_and_counted(tmp_path):
    path = tmp_path / "r.mcap"
    with McapRecorder(path) as rec:
        rec.write("operator/link", 1, {"x": float("nan"), "a": np.array([1.0, np.inf])})
    assert rec.records_nonfinite == 1
    (_, _, record), *_ = read_recording(path)
    assert record["x"] is None and sorted(record["_nonfinite"]) == ["a", "x"]
    assert record["a"][0] == 1.0 and np.isnan(record["a"][1])


def test_the_caller_may_reuse_its_array_after_write(tmp_path):
    path = tmp_path / "r.mcap"
    buf = np.zeros(3, np.float32)
    with McapRecorder(path) as rec:
        rec.write("robot/frame", 1, {"frame": buf})
        buf[:] = 7
    (_, _, record), *_ = read_recording(path)
    assert not record["frame"].any()


@pytest.mark.slow
def test_writes_from_many_threads_all_arrive_in_order(tmp_path):
    path = tmp_path / "r.mcap"
    n_threads, n = 4, 3000
    with McapRecorder(path, flush_interval_s=0.05) as rec:

        def work(k: int) -> None:
            for i in range(n):
                rec.write(f"t{k}", i, {"i": i, "v": np.full(3, i, np.int32)})

        threads = [threading.Thread(target=work, args=(k,)) for k in range(n_threads)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    assert rec.records_dropped == 0
    seen: dict[str, list[int]] = {}
    for channel, _, record in read_recording(path):
        seen.setdefault(channel, []).append(record["i"])
    assert seen == {f"t{k}": list(range(n)) for k in range(n_threads)}


def test_a_full_queue_drops_and_counts_instead_of_growing(tmp_path):
    path = tmp_path / "r.mcap"
    total = 20_000
    with McapRecorder(path, max_queue=50, flush_interval_s=1.0) as rec:
        for i in range(total):
            rec.write("robot/frame", i, {"i": i})
    assert rec.records_dropped > 0
    assert rec.records_written + rec.records_dropped == total
    assert sum(1 for _ in read_recording(path)) == rec.records_written


def test_writes_after_close_are_dropped_not_raised(tmp_path):
    rec = McapRecorder(tmp_path / "r.mcap")
    rec.close()
    rec.close()
    rec.write("robot/frame", 1, {"i": 1})
    assert rec.records_dropped == 1


@pytest.mark.slow
def test_a_file_cut_at_any_byte_reads_back_every_whole_chunk(tmp_path):
    """A cut inside chunk k yields exactly the records of chunks 0..k-1, never an error."""
    path = tmp_path / "r.mcap"
    per_chunk, chunks = 7, 5
    with McapRecorder(path, flush_interval_s=3600) as rec:
        for c in range(chunks):
            for i in range(per_chunk):
                rec.write("robot/frame", c * per_chunk + i, {"i": c * per_chunk + i})
            assert rec.flush()
    data = path.read_bytes()
    whole = [r["i"] for _, _, r in read_recording(path)]
    assert whole == list(range(per_chunk * chunks))
    cut_path = tmp_path / "cut.mcap"
    counts = set()
    for cut in range(0, len(data), 3):
        cut_path.write_bytes(data[:cut])
        reader = RecordingReader(cut_path)
        got = [r["i"] for _, _, r in reader]
        assert got == whole[: len(got)], cut
        assert len(got) % per_chunk == 0, cut
        assert reader.truncated
        counts.add(len(got))
    assert counts == {per_chunk * k for k in range(chunks + 1)}


def test_damage_inside_a_closed_file_skips_the_bad_chunk_and_counts_its_records(tmp_path):
    """64 bytes flipped anywhere: every other chunk reads back, the loss is counted exactly."""
    path = tmp_path / "r.mcap"
    per_chunk, chunks = 30, 12
    with McapRecorder(path, flush_interval_s=3600, fsync=False) as rec:
        for i in range(per_chunk * chunks):
            rec.write("robot/frame", (i + 1) * 33_000_000, {"i": i, "x": np.random.rand(50)})
            if i % per_chunk == per_chunk - 1:
                assert rec.flush()
    data = path.read_bytes()
    bad = tmp_path / "bad.mcap"
    damaged = 0
    for at in range(20, len(data) - 64, len(data) // 23):
        flipped = bytearray(data)
        flipped[at : at + 64] = bytes(b ^ 0xFF for b in flipped[at : at + 64])
        bad.write_bytes(flipped)
        reader = RecordingReader(bad)
        got = [r["i"] for _, _, r in reader]
        lost = sum(n for d in reader.damage for n in d.records_lost.values())
        assert reader.complete and not reader.truncated, at  # it was closed cleanly
        assert got == sorted(got) and len(got) + lost == per_chunk * chunks, at
        missing = sorted(set(range(per_chunk * chunks)) - set(got))
        assert len(missing) % per_chunk == 0, at  # whole chunks (none: an index was hit)
        if not missing:
            continue
        damaged += 1
        damage = reader.damage[0]
        assert damage.t_before_ns is None or damage.t_before_ns < (missing[0] + 1) * 33_000_000
        if damage.t_after_ns is not None:
            assert damage.t_after_ns > (missing[-1] + 1) * 33_000_000
    assert damaged > 15  # most flips hit a chunk: they are most of the file


def test_a_file_that_is_not_mcap_is_named_so(tmp_path):
    path = tmp_path / "notes.mcap"
    path.write_bytes(b"this is not a recording at all\n")
    with pytest.raises(RecordingError, match="not an MCAP file"):
        list(RecordingReader(path))


@pytest.mark.slow
def test_sigkill_loses_at_most_the_last_second(tmp_path):
    path = tmp_path / "killed.mcap"
    rate_hz = 200.0
    child = subprocess.Popen(
        [sys.executable, str(HERE / "record_until_killed.py"), str(path), str(rate_hz)],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        flushes = []
        deadline = time.monotonic() + 20
        while len(flushes) < 3 and time.monotonic() < deadline:
            line = child.stdout.readline()
            if line.startswith("flushed"):
                flushes.append(int(line.split()[1]))
        assert len(flushes) == 3, "the child reported no flushes"
        time.sleep(0.7)  # kill in the middle of a flush interval
        t_kill = time.monotonic_ns()
        os.kill(child.pid, signal.SIGKILL)
        child.wait(timeout=5)
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
    assert child.returncode == -signal.SIGKILL
    reader = RecordingReader(path)
    got = [(t, r["frame_seq"]) for _, t, r in reader]
    assert reader.truncated and not reader.complete
    # everything the child saw flushed is there, in order, without a gap
    assert len(got) >= flushes[-1]
    assert [i for _, i in got] == list(range(len(got)))
    lost_s = (t_kill - got[-1][0]) / 1e9
    assert lost_s <= 1.0 + 0.3, f"lost the last {lost_s:.2f} s"


def test_a_cut_file_is_recovered_with_an_index(tmp_path):
    from mcap.reader import make_reader

    path = tmp_path / "r.mcap"
    with McapRecorder(path, flush_interval_s=3600, metadata={"m": {"a": "b"}}) as rec:
        for i in range(30):
            rec.write("robot/frame", i, {"i": i, "f": np.full(3, i, np.float32)})
            if i % 10 == 9:
                assert rec.flush()
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])  # the footer, the summary and a chunk are gone
    expected = list(read_recording(cut))
    assert 0 < len(expected) < 30
    out = tmp_path / "recovered.mcap"
    assert recover_recording(cut, out) == len(expected)
    reader = RecordingReader(out)
    got = list(reader)
    assert reader.complete and not reader.truncated
    assert [(c, t, r["i"]) for c, t, r in got] == [(c, t, r["i"]) for c, t, r in expected]
    assert read_metadata(out)["m"] == {"a": "b"}
    with open(out, "rb") as f:  # the mcap package's seeking reader uses the index
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics.message_count == len(expected)
