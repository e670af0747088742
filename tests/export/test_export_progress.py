"""`deepxpalm export`'s progress: a bar on a terminal; in a pipe, plain lines only."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from synthetic import robot_recording
from tests_support import stderr_on_pty

REPO = Path(__file__).resolve().parents[2]
CONTROL = re.compile(r"[\r\x1b\x00-\x08\x0b-\x1f\x7f]")

pytestmark = [pytest.mark.slow, pytest.mark.untimed]  # two exports, no timing asserted


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("rec") / "robot.mcap"
    robot_recording(path, 10.0)
    return path


def _argv(recording: Path, out: Path) -> list[str]:
    return [sys.executable, "-m", "deploy.cli", "export", str(recording), "--out", str(out),
            "--episodes", "session", "--fps", "30", "--json"]  # fmt: skip


def _env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("CI", "TERM")}
    return dict(env, PYTHONPATH=str(REPO), TERM="xterm")


def test_piped_the_export_writes_a_line_per_tenth_and_its_json_stays_clean(recording, tmp_path):
    proc = subprocess.run(
        _argv(recording, tmp_path / "ds"), env=_env(), capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert json.loads(proc.stdout)["frames"] > 0
    lines = [line for line in proc.stderr.splitlines() if line.startswith("export: ")]
    assert 1 <= len(lines) <= 10, proc.stderr
    assert re.match(r"export: \d+ % \([\d.]+/[\d.]+ s recorded\), \d+:\d\d so far, ETA", lines[0])
    assert not CONTROL.search(proc.stderr.replace("\n", "")), proc.stderr[-500:]


def test_on_a_terminal_the_export_draws_a_bar(recording, tmp_path):
    seen, rc = stderr_on_pty(_argv(recording, tmp_path / "ds"), _env(), cwd=REPO)
    assert rc == 0, seen[-2000:]
    bars = [u for u in seen.decode(errors="replace").split("\r") if u.startswith("export [")]
    # a short export may end before the first redraw: its bar then shows "ETA ?" only
    assert any(re.search(r"s recorded \d+:\d\d ETA (\?|\d+:\d\d)", u) for u in bars), bars
