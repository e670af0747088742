"""The Markdown report, the JSON beside it, and the figures.

The report states its conditions first (machine, load, pinning, sizes),
then the verdicts against the issue's targets, then whether each default in
the code is the one the measurements favour, then every table. Numbers
come only from the results dictionary, which is also the JSON file, so the
two cannot disagree. Everything after the conditions is the sections'
own (the table in harness/bench/sections.py), in its order, then the presets.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

from harness.bench.fmt import num, results_of, table
from harness.bench.section import Verdict
from harness.bench.sections import SECTIONS

log = logging.getLogger(__name__)
#: 8N1: a start bit, eight data bits, a stop bit
BITS_PER_BYTE_ON_THE_LINE = 10


def markdown(results: dict[str, Any]) -> str:
    """The whole report: the run's conditions, then what each section in the table claims."""
    m = results["machine"]
    lb, la = m["load_before"], m["load_after"]
    v = results["versions"]
    out: list[str] = [
        "# Benchmarks: run time against error, and the latency budget",
        "",
        f"Regenerate with `{results['generated_by']} --update-docs` from the repository root "
        "(without `--update-docs` a run writes to runs/bench/<date-time>/; `deepxpalm bench "
        "--quick` runs in under 90 s, see [Presets](#presets-what---quick-measures)). Written "
        "by `harness/bench`; every number below is also in [benchmarks.json](benchmarks.json).",
        "",
        "## Conditions",
        "",
        f"- {results['date']}, commit `{results['git_commit']}`, preset `{results['preset']}`, "
        f"{results['total_seconds']} s.",
        f"- {m['cpu']}, {m['cores']} cores, Linux {m['kernel']}; the bench process pinned to "
        f"core {m['pinned_core']}, BLAS/OpenMP, torch and ONNX Runtime at one thread.",
        f"- **Machine load** (1/5/15 min averages): {lb['loadavg_1m']}/{lb['loadavg_5m']}/"
        f"{lb['loadavg_15m']} before, {la['loadavg_1m']}/{la['loadavg_5m']}/"
        f"{la['loadavg_15m']} after, on {m['cores']} cores shared with other work: "
        "tails (p99) carry other processes' preemptions, medians much less so.",
        f"- Python {v['python']}, numpy {v['numpy']}, pyzmq {v['pyzmq']}, "
        f"numba {v.get('numba')}, onnxruntime "
        f"{v['onnxruntime']}, torch {v['torch']}, scipy {v['scipy']}.",
        f"- Timer: `perf_counter_ns`, {results['timer_overhead_ns']:.0f} ns per pair of reads "
        "(included in every stage time).",
        f"- One thread wake-up (a sleep of 1/240 s) costs "
        f"{results.get('wakeup_cpu_us', float('nan')):.0f} us of CPU here; on a bare-metal "
        "PC it is a few microseconds. The nodes wake several threads per frame, so on this "
        "VM wake-ups, not computation, dominate their CPU share (see Node CPU).",
        _cold_line(results),
        _gc_line(results),
        *_remeasured_lines(results),
        "",
        "## Verdicts",
        "",
    ]
    out += table(
        ["target", "measured", "verdict"],
        [
            [v.what, v.measured or "not run", _ok(v.passed) if v.measured else "n/a"]
            for v in summary_verdicts(results)
        ],
    )
    out += ["", "## Defaults in the code against the measurements", ""]
    out += table(
        ["setting", "default", "favoured by the measurements", "agrees", "evidence"],
        [
            [
                f"`{c.setting}`",
                f"`{c.default}`",
                f"`{c.best}`",
                "n/a" if c.agrees is None else ("yes" if c.agrees else "**no**"),
                c.why,
            ]
            for s in SECTIONS
            for c in s.default_checks(results)
        ],
    )
    for s in SECTIONS:
        out += s.markdown(results)
    out += _failures_md(results)
    out += _presets_md()
    out += _limits_md()
    return "\n".join(out) + "\n"


def summary_verdicts(results: dict[str, Any]) -> list[Verdict]:
    """The verdict table's rows: every section's targets, then the checks any machine must pass."""
    every = [v for s in SECTIONS for v in s.verdicts(results)]
    return [v for kind in ("target", "check") for v in every if v.table == kind]


def _ok(flag: bool | None) -> str:
    return "not valid" if flag is None else ("**pass**" if flag else "**FAIL**")


def _gc_line(results: dict[str, Any]) -> str:
    g = results.get("full_collection")
    if not g:
        return "- Garbage collector: not measured."
    return (
        f"- A full garbage collection walks {g['objects']:,.0f} objects in this bench process "
        f"(the robot stack, and torch for the comparisons) and takes {num(g['as_is_ms'])} ms; "
        "a robot node, which never loads torch, holds fewer. After `gc.freeze()`, which "
        f"both nodes call once built (`common.process.command_line.freeze_startup_heap`), "
        f"{num(g['frozen_ms'] * 1e3)} us. Unfrozen, such a pass would stall a 60 Hz loop "
        "whenever the collector chose to run one."
    )


def _cold_line(results: dict[str, Any]) -> str:
    c = results.get("cold_call")
    if not c:
        return ""
    return (
        f"- A pure-Python IK call takes {c['warm_us']:.1f} us back to back and "
        f"{c['first_after_gap_us']:.1f} us as the first call after {c['gap_ms']:g} ms of "
        "other work on the same core (the thread never left it): the core's caches and "
        "predictors are cold again after a frame period. This, on this VM, is why paced "
        "numbers below are several times the back-to-back ones; a dedicated robot PC with "
        "nothing else running will sit between the two, and should be measured there."
    )


_WHY_SKIPPED = {"skip": "`--skip`", "quick": "left out of `--quick`"}


def _failures_md(results: dict[str, Any]) -> list[str]:
    bad = {k: v for k, v in results["sections"].items() if isinstance(v, dict) and "error" in v}
    skipped = {
        k: v for k, v in results["sections"].items() if isinstance(v, dict) and v.get("skipped")
    }
    out: list[str] = []
    if bad or skipped:
        out += ["", "## Sections not measured", ""]
        out += [f"- `{k}` failed: {v['error']}" for k, v in bad.items()]
        out += [
            f"- `{k}` skipped ({_WHY_SKIPPED[v.get('why', 'skip')]})" for k, v in skipped.items()
        ]
    return out


def _presets_md() -> list[str]:
    """What ``--quick`` measures of each section, from the sections' own sizes."""
    from dataclasses import asdict

    from harness.bench.sections import SECTIONS

    def sizes(s: Any) -> str:
        return ", ".join(
            f"{k} {'/'.join(map(str, v)) if isinstance(v, tuple) else v}"
            for k, v in asdict(s).items()
        )

    rows = [
        [
            f"`{s.name}`",
            sizes(s.sizes["quick"]) if s.quick else "left out (`--only` runs it at its quick size)",
            sizes(s.sizes["full"]),
        ]
        for s in SECTIONS
    ]
    return [
        "",
        "## Presets: what `--quick` measures",
        "",
        "`deepxpalm bench --quick` is meant to finish in under 90 s on two shared cores: it "
        "keeps the sections that run in the bench's own process, at smaller sizes, and leaves "
        "out those that start node processes, a browser or task trials, whose start-up alone "
        "costs tens of seconds on a loaded machine. Sizes per section (the full run's beside "
        "them):",
        "",
        *table(["section", "--quick", "full run"], rows, "|---|---|---|"),
    ]


def _limits_md() -> list[str]:
    from robot_side.tactile.wire import DEFAULT_BAUD, N_PADS, PACKET_SIZE

    scan_ms = 1e3 * N_PADS * PACKET_SIZE * BITS_PER_BYTE_ON_THE_LINE / DEFAULT_BAUD
    return [
        "",
        "## What these numbers do not cover",
        "",
        f"- A real serial line (the UART's {scan_ms:.1f} ms per scan at {DEFAULT_BAUD} baud, "
        "USB latency) and "
        "real servos: the chain starts at bytes in memory and ends at packet bytes.",
        "- CURVE encryption (off here; the nodes enable it for remote links) and network "
        "impairment (deepxpalm netsim covers that).",
        "- A GPU, and any CPU but this one; a shared VM's tails are not a dedicated robot "
        "PC's tails.",
        "- Classifier accuracy on real frames: every frame here is synthetic.",
    ]


def _remeasured_lines(results: dict[str, Any]) -> list[str]:
    later = results.get("remeasured") or {}
    return [
        f"- Section `{name}` re-measured alone ({r['generated_by']}), run finished "
        f"{r['date']}, commit `{r['git_commit']}`, machine load (1 min) "
        f"{r['load_before']} before and {r['load_after']} after."
        for name, r in sorted(later.items())
    ]


def merge_sections(existing_json: Path, fresh: dict[str, Any], names: list[str]) -> dict[str, Any]:
    """``fresh``'s sections ``names`` in the report already at ``existing_json`` (if any).

    The report keeps its own conditions; the merged sections are listed with theirs.
    """
    import json
    from dataclasses import asdict

    if not existing_json.exists():
        return fresh
    merged = json.loads(existing_json.read_text())
    stamp = {
        "generated_by": fresh["generated_by"],
        "date": fresh["date"],
        "git_commit": fresh["git_commit"],
        "load_before": fresh["machine"]["load_before"]["loadavg_1m"],
        "load_after": fresh["machine"]["load_after"]["loadavg_1m"],
    }
    from harness.bench.sizes import PRESETS

    for name in names:
        merged["sections"][name] = fresh["sections"][name]
        merged.setdefault("remeasured", {})[name] = stamp
        # the measured sections' own sizes are the fresh run's; any new key joins too
        own = set(asdict(PRESETS["full"][name]))
        merged["sizes"].update(
            {k: v for k, v in fresh["sizes"].items() if k in own or k not in merged["sizes"]}
        )
    return merged


# ------------------------------------------------------------------ outputs
def write_outputs(results: dict[str, Any], out_dir: Path, figures: bool = True) -> list[Path]:
    """docs/benchmarks.md, docs/benchmarks.json and docs/img/bench_*.png."""
    out_dir.mkdir(parents=True, exist_ok=True)
    img = out_dir / "img"
    paths: list[Path] = []
    if figures:
        img.mkdir(exist_ok=True)
        for section in SECTIONS:
            s = results_of(results, section.name)
            if s is None or section.figure is None:
                continue
            try:
                paths.append(section.figure(s, img / f"bench_{section.name}.png"))
            except ImportError as e:
                log.warning("no figures (%s): install matplotlib (the train extra)", e)
                break
    md = out_dir / "benchmarks.md"
    md.write_text(markdown(results))
    for section in SECTIONS:
        s = results_of(results, section.name)
        if s is not None:
            paths += section.update_other_docs(s, out_dir)
    js = out_dir / "benchmarks.json"
    slim = json.loads(json.dumps(results, default=str))
    for v in slim["sections"].values():
        if isinstance(v, dict):
            v.pop("trace", None)
    js.write_text(json.dumps(slim, indent=1) + "\n")
    return [md, js, *paths]
