"""``deepxpalm bench``: measure the loop, write benchmarks.md, .json and the figures.

    deepxpalm bench                  # the full run: about 1 h 45 min (below)
    deepxpalm bench --quick          # under 90 s: the in-process sections, smaller samples
    deepxpalm bench --quick --only netsim         # one left-out section at its quick size
    deepxpalm bench --update-docs    # the full run, written over docs/ (the committed report)
    deepxpalm bench --only netsim --update-docs   # re-measure one section into docs/
    deepxpalm bench --out /tmp/bench --skip node_cpu
    deepxpalm bench --only task --task-cells runs/task --update-docs   # resumable, cell by cell

The full run's time is its sections' as the committed report measured them
(docs/benchmarks.json; the task table's, its cells' own), about 1 h 45 min on two
shared cores: the task table's twelve cells about 77 minutes of it, the fault
matrix 8, the other fifteen sections 18. With --task-cells an interrupted
task table resumes where it stopped. On a terminal a bar shows the section,
its cells or trials and an ETA from the last stored run of the same preset
(none yet: "ETA ?"); in a log or CI a plain line per section and per tenth.

A run writes to a folder of its own (runs/bench/<date-time>/) unless told
--out or --update-docs, so trying it never dirties the committed report.
With --only, the sections measured replace those in the folder's existing
benchmarks.json and the rest is kept; each section says when it was measured.

One process, pinned to one core, with BLAS/OpenMP pools at one thread and
torch and ONNX Runtime at one intra-op thread, so every number is a
one-core number. The machine's load is recorded before and after, because
on a shared machine it is part of every number.
"""

from __future__ import annotations

from harness.bench.timing import limit_thread_pools

# Thread pools are sized when numpy (OpenBLAS) and torch are first imported,
# which happens below this line, never before (deploy.cli imports no numpy).
limit_thread_pools()

import argparse  # noqa: E402
import logging  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

from harness.bench.sections import SECTION_NAMES as SECTIONS  # noqa: E402
from harness.bench.sections import SECTIONS as SECTION_TABLE  # noqa: E402
from harness.bench.sizes import PRESETS  # noqa: E402

log = logging.getLogger(__name__)

#: the sections --quick measures only when named with --only
QUICK_LEAVES_OUT = tuple(s.name for s in SECTION_TABLE if not s.quick)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.description = __doc__
    size = parser.add_mutually_exclusive_group()
    size.add_argument(
        "--quick",
        action="store_true",
        help="under 90 s: smaller samples, scale modelled only, and leaves out the sections "
        f"that start processes, a browser or trials ({', '.join(QUICK_LEAVES_OUT)}; "
        "name one with --only to measure it at its quick size); docs/benchmarks.md",
    )
    size.add_argument(
        "--size", choices=sorted(PRESETS), help="a named preset (smallest is for the tests)"
    )
    where = parser.add_mutually_exclusive_group()
    where.add_argument(
        "--out",
        type=Path,
        help="where benchmarks.md, benchmarks.json and img/bench_*.png go "
        "(default: runs/bench/<date-time>)",
    )
    where.add_argument(
        "--update-docs",
        action="store_true",
        help="write over docs/benchmarks.md, .json and docs/img (the committed report)",
    )
    parser.add_argument(
        "--cpu", type=int, help="the core to pin to (default: the last one this process may use)"
    )
    parser.add_argument(
        "--models",
        type=Path,
        action="append",
        default=None,
        help="more classifier .npz files or folders to compare with the shipped model "
        "(default: runs/width-sweep if it exists, the perception width sweep's output)",
    )
    only_or_skip = parser.add_mutually_exclusive_group()
    only_or_skip.add_argument(
        "--skip", action="append", default=[], choices=SECTIONS, help="leave a section out"
    )
    only_or_skip.add_argument(
        "--only",
        action="append",
        default=[],
        choices=SECTIONS,
        help="measure only this section (repeatable) and merge it into the folder's report",
    )
    parser.add_argument(
        "--task-cells",
        type=Path,
        metavar="DIR",
        help="the task section saves each cell here as it ends and reads the cells already "
        "here instead of running them again: a long table resumes, and deleting one cell's "
        "file reruns that cell alone",
    )
    parser.add_argument("--no-figures", action="store_true", help="skip the PNGs")
    parser.add_argument(
        "--from-json",
        type=Path,
        metavar="PATH",
        help="measure nothing: rewrite the report and figures from a benchmarks.json",
    )


def output_folder(args: argparse.Namespace) -> Path:
    """Where this run writes: docs/ only when asked, else a folder of its own."""
    if args.update_docs:
        return Path("docs")
    if args.out is not None:
        return args.out
    import time

    return Path("runs/bench") / time.strftime("%Y%m%d-%H%M%S")


def preset_of(args: argparse.Namespace) -> str:
    return "quick" if args.quick else (args.size or "full")


def sections_to_skip(args: argparse.Namespace) -> set[str]:
    """--only's complement, or --skip's, and what --quick leaves out unless --only names it."""
    if args.only:
        return set(SECTIONS) - set(args.only)
    skip = set(args.skip)
    if preset_of(args) == "quick":
        skip |= set(QUICK_LEAVES_OUT)
    return skip


def run(args: argparse.Namespace) -> int:
    args.out = output_folder(args)
    if args.from_json is not None:
        import json

        from harness.bench.report import write_outputs

        results = json.loads(args.from_json.read_text())
        for p in write_outputs(results, args.out, figures=not args.no_figures):
            print(f"wrote {p}")
        return 0
    preset = preset_of(args)
    sizes = PRESETS[preset]
    skip = sections_to_skip(args)
    models = args.models
    if models is None:
        default_sweep = Path("runs/width-sweep")
        models = [default_sweep] if default_sweep.is_dir() else []
    from harness.bench.progress import BenchProgress, last_durations, stored_reports
    from harness.bench.report import write_outputs
    from harness.bench.runner import run_bench

    # the ETA: each section's time in the last stored run of this preset
    progress = BenchProgress(last_durations(preset, stored_reports(args.out)))
    try:
        results = run_bench(
            sizes, preset, skip, args.cpu, models, progress=progress, task_cells=args.task_cells
        )
    finally:
        progress.close()
    if args.only:
        from harness.bench.report import merge_sections

        results = merge_sections(args.out / "benchmarks.json", results, args.only)

    paths = write_outputs(results, args.out, figures=not args.no_figures)
    for p in paths:
        print(f"wrote {p}")
    failed = [k for k, v in results["sections"].items() if isinstance(v, dict) and "error" in v]
    if failed:
        print(f"sections that failed: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0
