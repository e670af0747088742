"""Where `deepxpalm bench` writes, and how a re-measured section joins an existing report."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from harness.bench.cli import QUICK_LEAVES_OUT, add_arguments, output_folder, sections_to_skip
from harness.bench.report import merge_sections


def parse(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    return parser.parse_args(list(argv))


def test_a_plain_run_never_writes_over_the_committed_report():
    folder = output_folder(parse())
    assert folder.parts[:2] == ("runs", "bench") and folder != Path("docs")
    assert output_folder(parse("--quick")).parts[:2] == ("runs", "bench")
    assert output_folder(parse("--update-docs")) == Path("docs")
    assert output_folder(parse("--out", "/tmp/x")) == Path("/tmp/x")


def test_quick_leaves_out_the_process_sections_unless_only_names_one():
    assert {"task", "faults", "netsim", "video"} <= set(QUICK_LEAVES_OUT)
    assert "stages" not in QUICK_LEAVES_OUT
    assert sections_to_skip(parse("--quick")) == set(QUICK_LEAVES_OUT)
    assert sections_to_skip(parse("--quick", "--skip", "ik")) == {"ik", *QUICK_LEAVES_OUT}
    assert "netsim" not in sections_to_skip(parse("--quick", "--only", "netsim"))
    assert sections_to_skip(parse()) == set()  # the full run measures every section


def _results(sections: dict, date: str, commit: str, load: float) -> dict:
    return {
        "generated_by": "deepxpalm bench",
        "date": date,
        "git_commit": commit,
        "sizes": {"a": 1},
        "machine": {"load_before": {"loadavg_1m": load}, "load_after": {"loadavg_1m": load}},
        "sections": sections,
    }


def test_only_replaces_the_sections_it_measured_and_says_when(tmp_path):
    old = _results({"ik": {"x": 1}, "netsim": {"x": 1}}, "then", "aaa", 0.5)
    (tmp_path / "benchmarks.json").write_text(json.dumps(old))
    fresh = _results({"ik": {"skipped": True}, "netsim": {"x": 2}}, "now", "bbb", 1.5)
    fresh["sizes"]["netsim_seconds"] = 20.0
    merged = merge_sections(tmp_path / "benchmarks.json", fresh, ["netsim"])
    assert merged["sections"] == {"ik": {"x": 1}, "netsim": {"x": 2}}
    assert merged["date"] == "then" and merged["git_commit"] == "aaa"
    assert merged["remeasured"]["netsim"]["git_commit"] == "bbb"
    assert merged["sizes"]["netsim_seconds"] == 20.0


def test_only_into_an_empty_folder_is_the_run_itself(tmp_path):
    fresh = _results({"netsim": {"x": 2}}, "now", "bbb", 1.5)
    assert merge_sections(tmp_path / "benchmarks.json", fresh, ["netsim"]) is fresh


def test_every_preset_writes_the_flat_sizes_the_committed_report_holds():
    """Each section keeps its own sizes; together they are the JSON's one flat dict."""
    from harness.bench.sizes import PRESETS

    committed = json.loads(Path("docs/benchmarks.json").read_text())["sizes"]
    full = PRESETS["full"].flat()
    assert full.keys() == committed.keys()
    assert json.loads(json.dumps(full)) == committed
    for sizes in PRESETS.values():
        assert sizes.flat().keys() == full.keys()


def test_a_remeasured_section_brings_its_own_sizes_and_leaves_the_others(tmp_path):
    old = _results({"task": {"x": 1}, "netsim": {"x": 1}}, "then", "aaa", 0.5)
    old["sizes"].update(parallel_cells=3, netsim_seconds=10.0)
    (tmp_path / "benchmarks.json").write_text(json.dumps(old))
    fresh = _results({"task": {"x": 2}, "netsim": {"x": 2}}, "now", "bbb", 1.5)
    fresh["sizes"].update(parallel_cells=1, netsim_seconds=20.0)
    merged = merge_sections(tmp_path / "benchmarks.json", fresh, ["task"])
    assert merged["sizes"]["parallel_cells"] == 1  # the task ran its cells one at a time
    assert merged["sizes"]["netsim_seconds"] == 10.0  # netsim was not measured again
