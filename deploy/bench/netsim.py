"""Bench section: the link simulator measured from outside, against its scenarios.

Runs ``common.netsim.fidelity`` (a PUB at 100 Hz to a SUB directly and to
another through ``deepxpalm netsim`` in byte-stream mode, on loopback) for
the transparent case and the delayed scenarios, and renders the table that
docs/benchmarks.md and docs/netsim.md both carry. The section also runs on
its own and rewrites the block in docs/netsim.md:

    python -m deploy.bench.netsim --seconds 20 --update docs/netsim.md

As a bench section: the link simulator measured from outside, against its scenarios.
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from deploy.bench.fmt import results_of
from deploy.bench.section import Context, Results, Section

SCENARIOS = ("none", "lan", "metro", "intercontinental", "loopback_trace")  # as the full preset
BEGIN, END = "<!-- netsim-fidelity:begin -->", "<!-- netsim-fidelity:end -->"


def fidelity(seconds: float, scenarios: tuple[str, ...] = SCENARIOS) -> dict[str, Any]:
    """One rig run per scenario; the simulator gets every core the bench had before pinning."""
    from common.netsim.fidelity import measure as run_rig

    try:
        from deploy.bench.timing import original_affinity

        cpus: set[int] | None = original_affinity()
    except (ImportError, OSError):
        cpus = None
    runs = [run_rig(name, seconds=seconds, netsim_cpus=cpus).as_dict() for name in scenarios]
    load = os.getloadavg()
    return {
        "seconds_per_scenario": seconds,  # the runner writes the section's total as "seconds"
        "date": time.strftime("%Y-%m-%d"),
        "runs": runs,
        "loadavg_after": [round(x, 2) for x in load],
    }


def _ms(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.2f}"


def _us(x: float | None) -> str:
    return "n/a" if x is None else str(round(x))


def fidelity_table(section: dict[str, Any] | None) -> list[str]:
    """The fidelity table (empty when the section was skipped or failed)."""
    if not section or "runs" not in section:
        return []
    out = [
        "## Link simulator fidelity (byte-stream mode, over real sockets)",
        "",
        "A PUB sends 100 messages a second carrying their send time, for "
        f"{section['seconds_per_scenario']:g} s, to a SUB directly and to another through "
        "`deepxpalm netsim` (its own process, stream mode) on loopback; the two paths "
        "alternate half a period apart. One-way delays in ms, to the operator. "
        "Target: configured + direct. "
        "Criteria: at zero delay, p50 within 0.15 ms and p99 within 0.5 ms of the direct "
        "link; with a delay, p5/p50/p95 within 0.5 ms or 5 % of the target. Load average "
        f"after: {', '.join(str(x) for x in section['loadavg_after'])} (2 shared cores).",
        "",
        "| scenario | direct p5 / p50 / p95 / p99 | configured p5 / p50 / p95 | "
        "through netsim p5 / p50 / p95 / p99 | netsim's own p50 / p99 (us) | criteria met |",
        "|---|---|---|---|---|---|",
    ]
    for r in section["runs"]:
        d, v, c = r["direct_ms"], r["via_ms"], r["configured_ms"]
        own = r.get("netsim_own_latency_us") or {}
        failed = [k for k, ok in r["verdicts"].items() if not ok]
        out.append(
            f"| {r['scenario']} | {_ms(d['p5'])} / {_ms(d['p50'])} / {_ms(d['p95'])} / "
            f"{_ms(d['p99'])} | {_ms(c['p5'])} / {_ms(c['p50'])} / {_ms(c['p95'])} | "
            f"{_ms(v['p5'])} / {_ms(v['p50'])} / {_ms(v['p95'])} / {_ms(v['p99'])} | "
            f"{_us(own.get('p50'))} / {_us(own.get('p99'))} | "
            f"{'yes' if r['ok'] else 'no (' + ', '.join(failed) + ')'} |"
        )
    out += [
        "",
        "netsim's own time runs from the kernel's receive timestamp of a chunk to its send "
        "returning, minus the scheduled delay: what the forwarder adds beyond the scenario. "
        "`lan` (0.1 ms) and `loopback_trace` (0.07 ms median) are below what an extra "
        "loopback hop costs here, so they come out at about the `none` row.",
        "",
    ]
    return out


def update_doc(path: Path, section: dict[str, Any]) -> None:
    """Replace the block between the markers in ``path`` with this run's table."""
    text = path.read_text()
    # the date the table was measured: a docs refresh from stored results keeps it
    # (results from before the section stored its date keep the one the page has)
    kept = re.search(re.escape(BEGIN) + r"\s*Measured (\d{4}-\d{2}-\d{2})", text)
    date = section.get("date") or (kept.group(1) if kept else "an unknown date")
    body = "\n".join(
        [
            BEGIN,
            f"Measured {date}; regenerate with "
            "`deepxpalm bench --only netsim --update-docs` or "
            "`python -m deploy.bench.netsim --update docs/netsim.md`.",
            "",
            *fidelity_table(section)[2:],
            END,
        ]
    )
    pattern = re.compile(re.escape(BEGIN) + ".*?" + re.escape(END), re.S)
    if not pattern.search(text):
        raise ValueError(f"{path} has no {BEGIN} ... {END} block")
    path.write_text(pattern.sub(lambda _: body, text))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="the link simulator's fidelity table")
    parser.add_argument("--seconds", type=float, default=20.0, help="per scenario")
    parser.add_argument("--update", type=Path, help="rewrite the block in this markdown file")
    args = parser.parse_args(argv)
    section = fidelity(args.seconds)
    if args.update:
        update_doc(args.update, section)
    print("\n".join(fidelity_table(section)))
    return 0


@dataclass(frozen=True)
class NetsimSizes:
    netsim_seconds: float  # per scenario, 100 messages a second
    netsim_scenarios: tuple[str, ...]


SIZES = {
    "full": NetsimSizes(netsim_seconds=20.0, netsim_scenarios=SCENARIOS),
    "quick": NetsimSizes(netsim_seconds=5.0, netsim_scenarios=SCENARIOS),
    "smallest": NetsimSizes(netsim_seconds=1.0, netsim_scenarios=("none",)),
}


def measure(ctx: Context, sizes: NetsimSizes) -> dict[str, Any]:
    return fidelity(sizes.netsim_seconds, sizes.netsim_scenarios)


def markdown(results: Results) -> list[str]:
    """The fidelity table docs/netsim.md carries too; nothing when the section did not run."""
    lines = fidelity_table(results_of(results, "netsim"))
    return ["", *lines] if lines else []


def update_netsim_doc(section: dict[str, Any], out_dir: Path) -> list[Path]:
    """docs/netsim.md carries the same table between its markers, when the folder has it."""
    page = out_dir / "netsim.md"
    if not page.exists():
        return []
    update_doc(page, section)
    return [page]


SECTION = Section(
    name="netsim",
    title="Link simulator fidelity",
    sizes=SIZES,
    measure=measure,
    markdown=markdown,
    update_other_docs=update_netsim_doc,
    quick=False,
)


if __name__ == "__main__":
    sys.exit(main())
