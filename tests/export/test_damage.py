"""`deepxpalm export`, run as a user runs it, on a damaged, a foreign or a misplaced file."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pyarrow.parquet as pq
import pytest
from synthetic import flip, robot_recording

from common.recording.mcap_recorder import read_recording
from deploy.export.cli import EXIT_DAMAGED

#: every test runs `deepxpalm export` as a user does, in a process of its own (its imports
#: alone are seconds of CPU): slow, and no timing asserted
pytestmark = [pytest.mark.slow, pytest.mark.untimed]

FPS = 30


def _export(*args):
    return subprocess.run(
        [sys.executable, "-m", "deploy.cli", "export", *map(str, args), "--no-progress"],
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_a_flip_at_40_percent_exports_every_intact_chunk_and_says_what_was_lost(tmp_path):
    rec = tmp_path / "robot.mcap"
    robot_recording(rec, 20.0)
    frames_t = [t for ch, t, _ in read_recording(rec) if ch == "robot/frame"]
    flip(rec, 0.4)
    out = tmp_path / "ds"
    proc = _export(rec, "--out", out, "--episodes", "session", "--fps", FPS, "--json")
    assert proc.returncode == EXIT_DAMAGED, proc.stderr[-2000:]
    assert "--accept-damage" in proc.stderr
    summary = json.loads(proc.stdout)
    (damage,) = summary["damage"]
    read_t = [t for ch, t, _ in read_recording(rec) if ch == "robot/frame"]
    lost = sorted(set(frames_t) - set(read_t))
    # one chunk is a recorded second: 33 or 34 frames, all in the range the summary names
    assert damage["frames_lost"] == len(lost) and 33 <= len(lost) <= 34
    assert damage["lost_from_ns"] < lost[0] and lost[-1] < damage["lost_to_ns"]
    assert 0.3 * 20 < damage["lost_from_s"] < damage["lost_to_s"] < 0.5 * 20
    # every intact chunk is exported: two episodes, one each side of the lost second
    meta = json.loads((out / "meta" / "deepxpalm.json").read_text())
    assert meta["sessions"][0]["robot_closed_cleanly"] is True
    eps = pq.read_table(out / "meta/episodes/chunk-000/file-000.parquet").to_pylist()
    assert len(eps) == 2
    for ep in eps:
        t = ep["deepxpalm/t_first_ns"] + np.arange(ep["length"]) * 1e9 / FPS
        assert not ((t > damage["lost_from_ns"]) & (t < damage["lost_to_ns"])).any()
    span_s = (frames_t[-1] - frames_t[0]) / 1e9
    gap_s = (damage["lost_to_ns"] - damage["lost_from_ns"]) / 1e9
    assert abs(summary["frames"] - (span_s - gap_s) * FPS) <= 3  # rows on both sides, all of them
    accepted = _export(rec, "--out", tmp_path / "ds2", "--episodes", "session", "--accept-damage")
    assert accepted.returncode == 0, accepted.stderr[-2000:]
    assert f"{len(lost)} frames lost" in accepted.stdout


def test_a_file_that_is_not_a_recording_is_named_so(tmp_path):
    garbage = tmp_path / "robot.mcap"
    garbage.write_bytes(bytes(range(256)) * 40)
    proc = _export(garbage, "--out", tmp_path / "ds")
    assert proc.returncode == 1 and "not an MCAP file" in proc.stderr, proc.stderr[-2000:]
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    proc = _export(empty, "--out", tmp_path / "ds")
    assert proc.returncode == 2 and "empty (0 bytes)" in proc.stderr, proc.stderr[-2000:]
    assert not (tmp_path / "ds").exists()


def test_out_refuses_a_folder_that_holds_something_else(tmp_path):
    rec = tmp_path / "robot.mcap"
    robot_recording(rec, 2.0)
    out = tmp_path / "photos"
    out.mkdir()
    (out / "holiday.jpg").write_bytes(b"\xff\xd8")
    proc = _export(rec, "--out", out, "--episodes", "session")
    assert proc.returncode == 2 and "not empty" in proc.stderr, proc.stderr[-2000:]
    assert sorted(p.name for p in out.iterdir()) == ["holiday.jpg"]
    empty = tmp_path / "empty"
    empty.mkdir()
    assert _export(rec, "--out", empty, "--episodes", "session").returncode == 0
    again = _export(rec, "--out", empty, "--episodes", "session")
    assert again.returncode == 2 and "already holds a dataset" in again.stderr
