"""Section: the link simulator measured from outside, against its scenarios."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from deploy.bench.fmt import results_of
from deploy.bench.netsim_fidelity import SCENARIOS
from deploy.bench.section import Context, Results, Section


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
    from deploy.bench.netsim_fidelity import measure as fidelity

    return fidelity(sizes.netsim_seconds, sizes.netsim_scenarios)


def markdown(results: Results) -> list[str]:
    """The fidelity table docs/netsim.md carries too; nothing when the section did not run."""
    from deploy.bench.netsim_fidelity import markdown as fidelity_table

    lines = fidelity_table(results_of(results, "netsim"))
    return ["", *lines] if lines else []


def update_netsim_doc(section: dict[str, Any], out_dir: Path) -> list[Path]:
    """docs/netsim.md carries the same table between its markers, when the folder has it."""
    from deploy.bench.netsim_fidelity import update_doc

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
)
