"""The table of sections: what the runner, the report and the command line all read."""

from __future__ import annotations

import json
from pathlib import Path

from harness.bench.report import markdown, summary_verdicts
from harness.bench.sections import SECTION_NAMES, SECTIONS
from harness.bench.sizes import PRESETS


def _committed() -> dict:
    return json.loads(Path("docs/benchmarks.json").read_text())


def test_every_section_is_named_once_and_sized_for_every_preset():
    assert len(set(SECTION_NAMES)) == len(SECTIONS)
    for section in SECTIONS:
        assert set(section.sizes) == set(PRESETS), section.name


def test_the_committed_report_has_every_section_of_the_table():
    assert set(_committed()["sections"]) == set(SECTION_NAMES)


def test_issue_targets_come_before_the_checks_any_machine_must_pass():
    kinds = [v.table for v in summary_verdicts(_committed())]
    assert kinds == sorted(kinds, key=["target", "check"].index)
    assert "check" in kinds and "target" in kinds


def test_a_report_with_every_section_skipped_still_holds_together():
    results = _committed()
    results["sections"] = {name: {"skipped": True} for name in SECTION_NAMES}
    md = markdown(results)
    assert md.count("Not run.") >= 8
    for name in SECTION_NAMES:
        assert f"- `{name}` skipped (`--skip`)" in md
    assert all(v.passed is None for v in summary_verdicts(results))


def test_the_committed_report_renders_every_section_it_measured(tmp_path):
    """What ``deepxpalm bench --from-json docs/benchmarks.json`` writes: each measured
    section's table, none of them skipped (a section whose results grew a part its text did
    not expect, the four viewers beside the video's one, once ended the report in a crash)."""
    from deploy.cli import main as deepxpalm

    args = ["bench", "--from-json", "docs/benchmarks.json", "--out", str(tmp_path), "--no-figures"]
    assert deepxpalm(args) == 0
    md = (tmp_path / "benchmarks.md").read_text()
    assert "skipped (`--skip`)" not in md and "Not run." not in md
    assert md.count("\n## ") >= len(SECTION_NAMES)
