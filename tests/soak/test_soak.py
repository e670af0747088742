"""The long run: the demo on the "bad day" link, memory, CPU, drops and errors.

Not in the default suite (``-m "not soak"`` in pyproject's addopts); run with

    pytest -m soak tests/soak            # 30 minutes, DEEPXPALM_SOAK_MINUTES to change

or directly ``deepxpalm soak --minutes 30 --scenario bad_day`` for the JSON
report. Run it on an otherwise idle machine: CPU and latency figures measure
the machine as much as the code.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

MINUTES = float(os.environ.get("DEEPXPALM_SOAK_MINUTES", "30"))


@pytest.mark.soak
@pytest.mark.timeout(int(MINUTES * 60 + 900))
def test_soak_bad_day(tmp_path):
    out = tmp_path / "soak.json"
    cmd = [
        sys.executable,
        "-m",
        "deploy.cli",
        "soak",
        "--minutes",
        str(MINUTES),
        "--scenario",
        "bad_day",
        "--dir",
        str(tmp_path / "run"),
        "--out",
        str(out),
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=MINUTES * 60 + 800)
    report = json.loads(out.read_text())
    assert report["crashes"] == [], report["crashes"]
    assert report["nonfinite_values"] == 0
    assert report["servo_goals_out_of_limits"] == 0
    for name, growth in report["memory_growth_mb"].items():
        assert growth < report["criteria"]["memory_growth_below_mb"], (name, growth)
    assert all(r["mismatches"] == 0 for r in report["replay"].values()), report["replay"]
    assert report["passed"] and proc.returncode == 0, proc.stderr[-2000:]
