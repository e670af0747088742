"""The bench's progress: an ETA from the last stored run, a bar on a terminal, quiet in a pipe.

The two runs of ``deepxpalm bench`` below are the smallest preset's (as
tests/bench/test_bench_quick.py) and two in-process sections: the first is
piped and stores its sections' times, the second runs in a pseudo-terminal
and must draw the bar with an ETA from them. The sections are the two that
need no classifier (the bench loads none for them): the runs cost their
interpreter and imports, not measurements.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
from tests_support import stderr_on_pty

from harness.bench.progress import BenchProgress, last_durations, stored_reports

REPO = Path(__file__).resolve().parents[2]
SECTIONS = ("ik", "scale")
CONTROL = re.compile(rb"[\r\x1b\x00-\x08\x0b-\x1f\x7f]")


def _report(path: Path, preset: str, sections: dict, remeasured: dict | None = None) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    report = {"preset": preset, "sections": sections}
    if remeasured:
        report["remeasured"] = remeasured
    path.write_text(json.dumps(report))
    return path


def test_the_eta_reads_the_newest_run_of_the_same_preset(tmp_path):
    runs = tmp_path / "runs"
    older = _report(runs / "a" / "benchmarks.json", "quick", {"ik": {"seconds": 9.0}})
    os.utime(older, (1, 1))
    _report(
        runs / "b" / "benchmarks.json",
        "quick",
        {"ik": {"seconds": 4.0}, "stages": {"error": "boom"}, "video": {"skipped": True}},
    )
    _report(runs / "c" / "benchmarks.json", "full", {"ik": {"seconds": 30.0}})
    full = _report(
        tmp_path / "docs.json",
        "full",
        {
            "stages": {"seconds": 60.0},
            "netsim": {"seconds": 12.0},
            # cells read back from --task-cells: the table costs its cells' own time
            "task": {"seconds": 854.0, "resumed_cells": 9, "wall_s": 4602.1},
        },
        # a section re-measured at the quick size into the full report
        {"netsim": {"generated_by": "deepxpalm bench --size quick"}},
    )
    reports = stored_reports(None, runs, committed=full)
    assert last_durations("quick", reports) == {"ik": 4.0, "netsim": 12.0}
    assert last_durations("full", reports) == {"ik": 30.0, "stages": 60.0, "task": 4602.1}
    # the run's own folder comes first
    own = tmp_path / "own"
    _report(own / "benchmarks.json", "quick", {"ik": {"seconds": 2.5}})
    assert last_durations("quick", stored_reports(own, runs, full))["ik"] == 2.5


def test_the_estimate_follows_the_stored_times_this_runs_pace_and_the_steps():
    import io

    p = BenchProgress({"a": 10.0, "b": 30.0, "c": 60.0}, stream=io.StringIO(), terminal=False)
    p.begin(["a", "b", "c"])
    t = time.monotonic()
    p.current, p.started = "a", t
    share, eta, open_ = p.estimate(t + 4.0)
    assert (round(share, 3), eta, open_) == (0.04, 96.0, False)
    p.end("a", 20.0)  # twice as slow as last time: the rest is expected twice as long
    p.current, p.started = "b", t
    share, eta, open_ = p.estimate(t + 10.0)
    assert eta == pytest.approx(50.0 + 120.0)
    p.steps(1, 4, "cells")  # 10 s a cell: 30 s to go in b, whatever the stored time said
    share, eta, _ = p.estimate(t + 10.0)
    assert eta == pytest.approx(30.0 + 120.0)
    assert share == pytest.approx((10 + 30 / 4) / 100)
    p.end("b", 40.0)
    p.current, p.started = "c", t
    p.priors.pop("c")  # a section never measured at this preset: the ETA is a lower bound
    assert p.estimate(t)[2] is True
    p.close()


def test_a_section_stored_at_zero_seconds_counts_as_measured():
    """The scale model takes under 5 ms: stored as 0.0 s, a time, not a section never run."""
    import io

    p = BenchProgress({"scale": 0.0, "ik": 10.0}, stream=io.StringIO(), terminal=False)
    p.begin(["scale", "ik"])
    t = time.monotonic()
    p.current, p.started = "scale", t
    _, eta, open_ = p.estimate(t)
    assert (eta, open_) == (10.0, False)
    p.close()


def test_the_stated_run_time_is_the_sum_of_the_committed_reports_sections():
    """The help's and the README's full run time against the sections' own measured times."""
    import harness.bench.cli as cli
    from harness.bench.progress import section_seconds

    committed = json.loads((REPO / "docs" / "benchmarks.json").read_text())
    measured = sum(section_seconds(s) or 0.0 for s in committed["sections"].values())
    readme = (REPO / "README.md").read_text()
    for text in (cli.__doc__, readme):
        hours, minutes = re.search(r"full run:? about (\d+) h (\d+) min", text).groups()
        stated = int(hours) * 3600 + int(minutes) * 60
        assert abs(stated - measured) <= 0.15 * measured, (stated, measured)


def _bench(out: Path) -> list[str]:
    only = [a for name in SECTIONS for a in ("--only", name)]
    return [sys.executable, "-m", "deploy.cli", "bench", "--size", "smallest", *only,
            "--no-figures", "--out", str(out)]  # fmt: skip


def _env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("CI", "TERM")}
    env["PYTHONPATH"] = str(REPO)
    env.update(extra)
    return env


@pytest.fixture(scope="module")
def two_runs(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench-progress")
    piped = subprocess.run(
        _bench(out), cwd=REPO, env=_env(TERM="xterm"), capture_output=True, timeout=240
    )
    assert piped.returncode == 0, piped.stderr.decode()[-2000:]
    stored = json.loads((out / "benchmarks.json").read_text())
    tty, rc = stderr_on_pty(_bench(out), _env(TERM="xterm"), cwd=REPO)
    assert rc == 0, tty.decode(errors="replace")[-2000:]
    return piped, stored, tty


@pytest.mark.slow
@pytest.mark.untimed
def test_piped_the_bench_writes_a_plain_line_per_section_and_no_control_characters(two_runs):
    piped, stored, _ = two_runs
    for stream in (piped.stdout, piped.stderr):
        assert not CONTROL.search(stream.replace(b"\n", b"")), stream[-500:]
    lines = piped.stderr.decode().splitlines()
    for name in SECTIONS:  # each section's wall time, where the next run's ETA reads it
        assert stored["sections"][name]["seconds"] >= 0  # scale's model: under 5 ms, 0.0
        assert any(line.startswith(f"[bench] {name}: ") for line in lines), lines
    assert stored["sections"]["ik"]["seconds"] > 0
    assert len([line for line in lines if line.startswith("bench: ")]) <= 10


@pytest.mark.slow
@pytest.mark.untimed
def test_on_a_terminal_the_bench_draws_a_bar_with_an_eta_from_the_last_run(two_runs):
    _, _, tty = two_runs
    updates = [u for u in tty.decode(errors="replace").split("\r") if u.startswith("bench [")]
    assert updates, tty[-2000:]
    with_eta = [u for u in updates if re.search(r"\d+% \d/2 \w+ \d+:\d\d ETA \d+:\d\d", u)]
    assert with_eta, updates
    # the ETA is the stored run's: both sections were measured, so it is no lower bound
    assert not any("ETA >" in u or "ETA ?" in u for u in updates), updates
    assert "[bench] ik: " in tty.decode(errors="replace")
