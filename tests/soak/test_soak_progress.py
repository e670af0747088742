"""``deepxpalm soak`` says how far it is while it runs (it runs 30 minutes by default): the
project's one progress bar, redrawn on a terminal, with an ETA."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import pytest
from tests_support import stderr_on_pty

ROOT = Path(__file__).resolve().parents[2]

pytestmark = [pytest.mark.slow, pytest.mark.untimed]  # a short demo; no timing checked


def test_a_short_soak_shows_its_progress_and_eta(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if k not in ("CI", "TERM")}
    env["PYTHONPATH"] = str(ROOT)
    argv = [sys.executable, "-m", "deploy.cli", "soak", "--minutes", "0.1", "--sample-s", "2",
            "--no-replay", "--dir", str(tmp_path / "run")]  # fmt: skip
    seen, _ = stderr_on_pty(argv, env, cwd=ROOT, timeout_s=240.0)
    text = seen.decode(errors="replace")
    assert "\rsoak [" in text and "ETA" in text, text[-3000:]
    assert "starting the demo" in text and "processes" in text, text[-3000:]
    # the report still follows (its verdict is the soak's own business, under this load)
    assert json.loads((tmp_path / "run" / "soak.json").read_text())["minutes"] > 0
