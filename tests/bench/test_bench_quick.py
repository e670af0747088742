"""deepxpalm bench at its smallest size: every section runs and the report holds together.

No timing is asserted (the numbers of the smallest preset mean nothing and
the machine is shared); what is asserted is the structure of the report and
the stress results that must hold on any machine: zero non-finite outputs,
servo goals inside their limits, steps within the rate limit.
"""

from __future__ import annotations

import json
import math

import pytest

from harness.bench.report import write_outputs
from harness.bench.runner import run_bench
from harness.bench.sizes import PRESETS, SECTIONS

pytestmark = [pytest.mark.slow, pytest.mark.untimed]  # no timing asserted (above)

# Every section runs once, in the module's fixture (the processes' too), but six whose
# measurements other tests run: the keep-alive's timing in its arm process
# (tests/drivers/test_arm_process.py), the task's ``run_cell`` (tests/lab/test_task.py), the
# fault matrix's ``run_cells`` (tests/faults), the command path's flood rig
# (tests/system/test_command_path.py), the video's viewers (tests/video), and the video
# through netsim's page
# (tests/dashboard/test_video_netsim_browser.py, which calls its ``play``); their tables
# are rendered from the committed report by tests/bench/test_sections.py. Run here too
# they cost two minutes of the suite's 15.
PROCESS_SECTIONS = {"node_cpu", "e2e_tcp", "netsim"}
COVERED_ELSEWHERE = {"task", "faults", "command_path", "video", "video_netsim", "keep_alive"}


@pytest.fixture(scope="module")
def smallest(tmp_path_factory):
    results = run_bench(PRESETS["smallest"], "smallest", set(COVERED_ELSEWHERE), None, [])
    out = tmp_path_factory.mktemp("bench")
    paths = write_outputs(results, out)
    return results, out, paths


def test_every_section_ran_or_was_skipped_on_request(smallest):
    results, _, _ = smallest
    assert set(results["sections"]) == set(SECTIONS)
    for name, section in results["sections"].items():
        assert "error" not in section, f"{name}: {section.get('error')}"
        assert section.get("skipped", False) == (name in COVERED_ELSEWHERE), name


def test_report_files_and_structure(smallest):
    results, out, paths = smallest
    md = (out / "benchmarks.md").read_text()
    for heading in (
        "## Conditions",
        "## Verdicts",
        "## Defaults in the code against the measurements",
        "## Latency budget per stage",
        "## End to end: frame bytes to servo packet",
        "## Run time against error: downsizing and rendering order",
        "## Run time against error: classifier backends and model widths",
        "## Run time against error: inverse kinematics",
        "## Run time against error: skipping work",
        "## Scale: frame rate and streams per core",
        "## Numerical stress",
        "## Node CPU",
    ):
        assert heading in md, heading
    assert "Machine load" in md
    data = json.loads((out / "benchmarks.json").read_text())
    assert data["sections"].keys() == results["sections"].keys()
    for name in ("stages", "downsizing", "classifier", "ik", "skipping", "scale"):
        assert (out / "img" / f"bench_{name}.png").stat().st_size > 1000
    assert all(p.exists() for p in paths)


def test_stage_budget_covers_every_stage(smallest):
    section = smallest[0]["sections"]["stages"]
    stages = section["stages"]
    compiled = ["frame_step"] if section["compiled_step"] else []
    assert list(stages) == [
        "wire_decode",
        "calibration",
        "sanitize_contact",
        "classification",
        "render",
        *compiled,
        "encode",
        "zmq_transit_tcp",
        "decode",
        "ik_3_linkages",
        "counts_rate_limit",
        "servo_packet",
        "encode_signed",
        "decode_verified",
        "replay_window",
    ]
    for s in stages.values():
        assert s["n"] > 0 and s["median_us"] > 0 and s["p99_us"] >= s["median_us"]
    # the sums and totals are the node's path: the compiled step, not the three it replaces,
    # and an unsigned stream (the signed stages are what signing would cost instead)
    skipped = {"sanitize_contact", "classification", "render"} if compiled else set()
    skipped |= {"encode_signed", "decode_verified", "replay_window"}
    assert section["node_path"] == [k for k in stages if k not in skipped]
    e2e = smallest[0]["sections"]["e2e_inproc"]
    assert e2e["n"] > 0 and e2e["frames_without_packet"] == 0


def test_stress_has_no_nonfinite_output_and_respects_limits(smallest):
    st = smallest[0]["sections"]["stress"]
    assert st["total_nonfinite_outputs"] == 0
    for part in ("grid", "shell"):
        ik = st["ik"][part]
        assert ik["points"] > 0
        assert ik["nonfinite_angles"] == ik["nonfinite_angles_scalar"] == 0
        assert ik["nonfinite_counts"] == ik["fk_refused"] == 0
        assert ik["max_round_trip_mm"] < 1e-9
    r = st["renderer"]
    assert r["nonfinite_outputs"] == r["out_of_limits"] == r["exceptions"] == 0
    assert r["largest_step_counts"] <= r["max_step_counts_allowed"]
    f = st["rendering"]
    assert f["renders_checked"] > 0
    assert f["nonfinite_outputs"] == f["out_of_range"] == f["exceptions"] == 0
    assert f["more_than_one_cell_in_a_row"] == f["refused_by_codec"] == 0
    assert f["classifier_nonfinite"] == 0


def test_skipping_costs_no_more_than_the_dead_band(smallest):
    s = smallest[0]["sections"]["skipping"]
    rows = {r["kind"]: r for r in s["rows"]}
    for kind in ("no_contact", "identical_frame", "published"):
        assert rows[kind]["max_abs_diff_n"] == 0.0, kind
        assert rows[kind]["frames_with_other_cells"] == 0, kind
    assert rows["unchanged_stimulus"]["max_abs_diff_n"] <= s["deadband_n"] + 1e-6
    assert rows["unchanged_stimulus"]["frames_with_other_cells"] == 0


def test_fused_downsizing_is_an_exact_rewrite(smallest):
    ds = smallest[0]["sections"]["downsizing"]
    agree = ds["fused_agreement"]
    assert agree["max_abs_diff_fused_masked_n"] < 1e-4
    assert agree["same_cells_share"] == 1.0
    variants = {(r["variant"], r["order"]) for r in ds["rows"]}
    assert ("antialiased", "mask_then_peak") in variants
    assert ("fused_masked", "mask_then_peak") in variants
    assert ("two_products", "peak_then_mask") in variants
    # every variant renders the same cells: the match share cannot depend on the rewrite
    by = {(r["variant"], r["order"]): r["match_true"] for r in ds["rows"]}
    assert by[("two_products", "mask_then_peak")] == by[("antialiased", "mask_then_peak")]
    assert by[("fused_masked", "mask_then_peak")] == by[("antialiased", "mask_then_peak")]


@pytest.mark.slow
def test_process_sections_run(smallest):
    """The two-process TCP loop, node CPU and link simulator, at the smallest sizes."""
    results, out, _ = smallest
    for name in PROCESS_SECTIONS:
        assert "error" not in results["sections"][name], results["sections"][name].get("error")
    tcp = results["sections"]["e2e_tcp"]
    assert "error" not in tcp, tcp.get("error")
    assert tcp["received"] > 0 and tcp["median_us"] > 0
    cpu = results["sections"]["node_cpu"]
    assert "error" not in cpu, cpu.get("error")
    # /proc charges CPU by the 10 ms tick: over the smallest size's 2 s a node using about 1 %
    # may be charged none (0.0, read in two runs beside two busy loops, once for the robot
    # node); that the nodes worked is what their counters below say
    for name in ("robot", "operator"):
        assert math.isfinite(cpu[f"{name}_cpu_percent"]) and cpu[f"{name}_cpu_percent"] >= 0
    assert cpu["robot_stats"]["frames_captured"] > 0
    assert cpu["operator_stats"]["stimuli_received"] > 0
    netsim = results["sections"]["netsim"]
    assert "error" not in netsim, netsim.get("error")
    assert netsim["runs"][0]["n_via"] > 0
    md = (out / "benchmarks.md").read_text()
    for heading in ("## Node CPU", "## Link simulator fidelity"):
        assert heading in md, heading
