"""``deepxpalm bench``: measure the loop, write docs/benchmarks.md, .json and the figures.

    deepxpalm bench            # the full run (about 7 minutes; run it on a quiet machine)
    deepxpalm bench --quick    # about a minute, smaller samples, modelled scale
    deepxpalm bench --out /tmp/bench --skip node_cpu

One process, pinned to one core, with BLAS/OpenMP pools at one thread and
torch and ONNX Runtime at one intra-op thread, so every number is a
one-core number. The machine's load is recorded before and after, because
on a shared machine it is part of every number.
"""

from __future__ import annotations

from deploy.bench.timing import limit_thread_pools

# Thread pools are sized when numpy (OpenBLAS) and torch are first imported,
# which happens below this line, never before (deploy.cli imports no numpy).
limit_thread_pools()

import argparse  # noqa: E402
import logging  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

from deploy.bench.sizes import PRESETS, SECTIONS  # noqa: E402

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.description = __doc__
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true", help="about a minute: smaller samples")
    size.add_argument(
        "--size", choices=sorted(PRESETS), help="a named preset (smallest is for the tests)"
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=Path("docs"),
        help="where benchmarks.md, benchmarks.json and img/bench_*.png go (default: ./docs)",
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
    parser.add_argument(
        "--skip", action="append", default=[], choices=SECTIONS, help="leave a section out"
    )
    parser.add_argument("--no-figures", action="store_true", help="skip the PNGs")
    parser.add_argument(
        "--from-json",
        type=Path,
        metavar="PATH",
        help="measure nothing: rewrite the report and figures from a benchmarks.json",
    )


def run(args: argparse.Namespace) -> int:
    if args.from_json is not None:
        import json

        from deploy.bench.report import write_outputs

        results = json.loads(args.from_json.read_text())
        for p in write_outputs(results, args.out, figures=not args.no_figures):
            print(f"wrote {p}")
        return 0
    preset = "quick" if args.quick else (args.size or "full")
    sizes = PRESETS[preset]
    skip = set(args.skip)
    models = args.models
    if models is None:
        default_sweep = Path("runs/width-sweep")
        models = [default_sweep] if default_sweep.is_dir() else []
    from deploy.bench.report import write_outputs
    from deploy.bench.runner import run_bench

    results = run_bench(sizes, preset, skip, args.cpu, models, progress=True)

    paths = write_outputs(results, args.out, figures=not args.no_figures)
    for p in paths:
        print(f"wrote {p}")
    failed = [k for k, v in results["sections"].items() if isinstance(v, dict) and "error" in v]
    if failed:
        print(f"sections that failed: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0
