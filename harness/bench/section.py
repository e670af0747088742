"""What a bench section is: the interface the runner and the report iterate.

A section owns everything about one measurement: how much it measures per
preset, the measuring call, its part of the report, its figure and the
verdicts it can pass or fail. Adding one is a module ``harness/bench/<name>.py``
and a line in the table of ``harness/bench/sections.py``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

Results = dict[str, Any]


@dataclass(frozen=True)
class Verdict:
    """A claim a section's numbers pass or fail, computed from the results, never typed."""

    what: str
    measured: str | None
    passed: bool | None
    #: where the report's verdict table lists it: the issue's targets first, then the checks
    #: that must hold on any machine; None: only in the section's own text
    table: Literal["target", "check"] | None = "target"


@dataclass(frozen=True)
class DefaultCheck:
    """A default in the code against the one the measurements favour."""

    setting: str
    default: str
    best: str
    agrees: bool | None
    why: str


@dataclass
class Context:
    """State some sections share, built by the runner instead of closures over each other."""

    preset: str
    core: int
    models: list[Path]
    #: paced stage medians (what a frame costs in the field), filled in by the stages section
    stage_medians_us: dict[str, float] = field(default_factory=dict)
    #: one-way PUB to SUB over loopback TCP in one process, filled in by the stages section
    tcp_transit_us: float = 0.0
    #: where the task section saves each cell as it ends, and reads the cells already there
    #: instead of running them again (``deepxpalm bench --task-cells``); None: keep nothing
    task_cells: Path | None = None
    #: a section with cells or trials says how far it is: ``steps(done, total, unit, detail)``
    #: (the bench's bar and ETA); the runner sets it, a section only calls it
    steps: Callable[..., None] = field(default=lambda *_, **__: None, repr=False)
    #: a line worth a reader's eye (a failed cell), printed above the bar rather than through it
    say: Callable[[str], None] = field(default=print, repr=False)
    _demo_frames: list[Any] = field(default_factory=list, init=False, repr=False)
    _classifier: Any = field(default=None, init=False, repr=False)

    @property
    def classifier(self) -> Any:
        """The node's default classifier (shipped model, first installed backend), loaded on
        first use: a run of sections that classify nothing (``--only ik``) loads none."""
        if self._classifier is None:
            from robot_side.perception import load_classifier

            self._classifier = load_classifier()
        return self._classifier

    def demo_frames(self) -> list[Any]:
        """The demo scene's frames, made once for every section that drives the nodes."""
        if not self._demo_frames:
            from harness.bench.scene_frames import demo_frames

            cycles = 1.0 if self.preset == "full" else 0.3
            self._demo_frames.extend(demo_frames("demo", cycles)[0])
        return self._demo_frames


def _no_verdicts(results: Results) -> list[Verdict]:
    return []


def _no_checks(results: Results) -> list[DefaultCheck]:
    return []


def _no_other_docs(section: dict[str, Any], out_dir: Path) -> list[Path]:
    return []


@dataclass(frozen=True)
class Section:
    """One measurement of the bench, from its sizes to its verdicts.

    ``sizes`` maps a preset name (full, quick, smallest) to the section's own
    frozen dataclass of sizes. ``markdown`` and the others get the whole
    results, since a section may cite another's numbers (the end-to-end
    table cites the deployed nodes'). ``figure`` is None for a section
    without one; it writes ``img_dir / f"bench_{name}.png"``.
    """

    name: str
    title: str
    sizes: dict[str, Any]
    measure: Callable[[Context, Any], dict[str, Any]]
    markdown: Callable[[Results], list[str]]
    figure: Callable[[dict[str, Any], Path], Path] | None = None
    verdicts: Callable[[Results], list[Verdict]] = _no_verdicts
    default_checks: Callable[[Results], list[DefaultCheck]] = _no_checks
    #: other pages in the report's folder that carry this section's numbers, brought up to date
    update_other_docs: Callable[[dict[str, Any], Path], list[Path]] = _no_other_docs
    #: measured by ``--quick``; False for a section whose processes, browser or trials cost
    #: more than the quick run's 90 s allow (``--quick --only NAME`` still measures it)
    quick: bool = True
