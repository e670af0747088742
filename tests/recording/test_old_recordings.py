"""Recordings made before the Foxglove types still read: the reader, replay and export.

``fixtures/session-v1`` was written by the recorder as it was before (every
schema ``deepxpalm/<channel>``, the camera as a plain JSON record); see its
README. New recordings are covered by test_replay.py and the export tests.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("mcap", reason="recording needs the 'record' extra")

from mcap.reader import make_reader

from common.recording.mcap_recorder import RecordingReader, read_recording

REPO = Path(__file__).resolve().parents[2]
OLD = Path(__file__).parent / "fixtures" / "session-v1"


def test_the_fixture_is_of_the_old_format():
    for name in ("robot", "operator", "camera"):
        with open(OLD / f"{name}.mcap", "rb") as f:
            schemas = {s.name for s in make_reader(f).get_summary().schemas.values()}
        assert schemas and all(s.startswith("deepxpalm/") for s in schemas), schemas


def test_the_reader_gives_old_records_as_before():
    robot = RecordingReader(OLD / "robot.mcap")
    counts: dict[str, int] = {}
    for channel, _, record in robot:
        counts[channel] = counts.get(channel, 0) + 1
        if channel == "robot/frame":
            assert record["frame"].shape == (2, 10, 10) and record["frame"].dtype == "float32"
    assert robot.complete and not robot.damage
    assert counts == {
        "robot/frame": 51,
        "robot/prediction": 45,
        "robot/stimulus": 28,
        "robot/link": 21,
        "robot/arm": 21,
        "robot/gripper": 21,
    }
    pics = [r for c, _, r in read_recording(OLD / "camera.mcap") if c == "camera/image"]
    assert len(pics) == 10
    assert all(p["data"][:2] == b"\xff\xd8" and "timestamp" not in p for p in pics)


@pytest.mark.slow
@pytest.mark.untimed
@pytest.mark.parametrize("node", ["robot", "operator"])
def test_replay_checks_an_old_recording(node):
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "deploy.cli",
            "replay",
            str(OLD / f"{node}.mcap"),
            "--check",
            "--json",
        ],
        env={**os.environ, "PYTHONPATH": str(REPO)},
        capture_output=True,
        text=True,
        timeout=180,
    )
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    summary = json.loads(proc.stdout)
    assert summary["node"] == node and summary["mismatches"] == 0
    checked = summary["checked"]
    if node == "robot":
        assert checked["frames_replayed"] == 51
    else:
        assert checked["stimuli_rendered"] == 26


@pytest.mark.slow
@pytest.mark.untimed
def test_export_reads_an_old_session(tmp_path):
    pytest.importorskip("pyarrow", reason="export needs the 'dataset' extra")
    from deploy.export.cli import export
    from deploy.export.resample import ExportConfig

    summary = export([OLD], tmp_path / "ds", ExportConfig(fps=30, episodes="session"))
    assert summary["episodes"] == 1 and summary["frames"] >= 29
    assert not summary["damage"] and not summary["cut_short"]
    assert "observation.images.test_pattern" in summary["features"]
    assert "observation.arm.joints" in summary["features"]
