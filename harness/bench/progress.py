"""The bench's progress: which section, how far into its cells or trials, and an ETA.

The ETA comes from the last stored run: each section's wall time in the
newest report of the same preset that measured it (the run's own folder
first, then runs/bench/, then the committed docs/benchmarks.json), scaled by
how this run's finished sections compared with theirs. A section that reports
its cells or trials (``Context.steps``) is estimated from its own rate once
one has ended. The bar itself is ``common.progress``: redrawn on a terminal,
a plain line per section (and per tenth of the run) in a log or CI.
"""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path
from typing import Any, TextIO

from common.progress import Progress, clock

#: how often the bar is redrawn while a section without steps runs (a terminal only; the
#: bench is pinned to one core, so the ticker wakes seldom)
TICK_S = 1.0
#: stored reports read for the ETA, newest first
MAX_REPORTS = 20
#: this run's pace against the stored one is believed within these bounds
PACE_BOUNDS = (0.25, 4.0)


def report_preset(report: dict[str, Any], section: str) -> str:
    """The preset ``section`` of a stored report was measured at (a remeasure says its own)."""
    stamp = report.get("remeasured", {}).get(section)
    if stamp is None:
        return str(report.get("preset", "full"))
    _, _, size = str(stamp.get("generated_by", "")).partition("--size ")
    return size.split()[0] if size else "full"


def section_seconds(section: dict[str, Any]) -> float | None:
    """A stored section's wall time; a task table whose cells were read back costs theirs."""
    if not isinstance(section, dict) or section.get("skipped") or "error" in section:
        return None
    if section.get("resumed_cells") and section.get("wall_s") is not None:
        return float(section["wall_s"])
    seconds = section.get("seconds")
    return None if seconds is None else float(seconds)


def stored_reports(
    out_dir: Path | None,
    runs: Path = Path("runs/bench"),
    committed: Path = Path("docs/benchmarks.json"),
) -> list[Path]:
    """Where the last runs are: this run's folder, runs/bench/* newest first, docs/."""
    paths = [out_dir / "benchmarks.json"] if out_dir is not None else []
    if runs.is_dir():
        found = [p for p in runs.glob("*/benchmarks.json") if p.is_file()]
        found.sort(key=lambda p: p.stat().st_mtime, reverse=True)
        paths += found[:MAX_REPORTS]
    paths.append(committed)
    unique: list[Path] = []
    for p in paths:
        if p.is_file() and p.resolve() not in {u.resolve() for u in unique}:
            unique.append(p)
    return unique


def last_durations(preset: str, reports: list[Path]) -> dict[str, float]:
    """Each section's wall time in the first of ``reports`` that measured it at ``preset``."""
    out: dict[str, float] = {}
    for path in reports:
        try:
            report = json.loads(path.read_text())
        except (OSError, ValueError):
            continue
        for name, section in report.get("sections", {}).items():
            if name in out or report_preset(report, name) != preset:
                continue
            seconds = section_seconds(section)
            if seconds is not None:
                out[name] = seconds
    return out


class BenchProgress:
    """The section loop's progress, drawn by one ``common.progress.Progress``."""

    def __init__(
        self,
        priors: dict[str, float],
        *,
        stream: TextIO | None = None,
        terminal: bool | None = None,
    ) -> None:
        self.priors = priors
        self.bar = Progress("bench", stream=stream, terminal=terminal)
        self.names: list[str] = []
        self.took: dict[str, float] = {}
        self.current: str | None = None
        self.started = 0.0
        self.step: tuple[int, int, str, str] | None = None
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._ticker: threading.Thread | None = None

    # ---------------------------------------------------------------- the loop's calls
    def begin(self, names: list[str]) -> None:
        """The sections this run measures, in order."""
        self.names = list(names)
        self.bar.t0 = time.monotonic()
        if self.bar.terminal and self._ticker is None:
            self._ticker = threading.Thread(target=self._tick, name="bench-progress", daemon=True)
            self._ticker.start()

    def start(self, name: str) -> None:
        with self._lock:
            self.current, self.started, self.step = name, time.monotonic(), None
            self._show(force=True)

    def steps(self, done: int, total: int, unit: str, detail: str = "") -> None:
        """The running section's cells or trials: ``done`` of ``total``."""
        with self._lock:
            self.step = (done, total, unit, detail)
            self._show()

    def end(self, name: str, seconds: float, error: str | None = None) -> None:
        with self._lock:
            self.took[name] = seconds
            self.current, self.step = None, None
            k = len(self.took)
            eta, open_ = self.estimate()[1:3]
            state = f"failed after {seconds} s: {error}" if error else f"{seconds} s"
            lower = ">" if open_ and eta is not None else ""
            after = f"; ETA {lower}{clock(eta)}" if k < len(self.names) else ""
            self._show(draw=False)
            self.bar.note(f"[bench] {name}: {state} ({k}/{len(self.names)} sections{after})")

    def note(self, line: str) -> None:
        self.bar.note(line)

    def close(self) -> None:
        self._stop.set()
        if self._ticker is not None:
            self._ticker.join(timeout=2 * TICK_S)
        n = len(self.took)
        self.bar.close(f"[bench] {n} sections in {clock(self.bar.elapsed())}" if n else "")

    # ---------------------------------------------------------------- the estimate
    def pace(self) -> float:
        """This run's sections' time against the stored run's, over those both measured."""
        both = [n for n in self.took if self.priors.get(n)]
        if not both:
            return 1.0
        ratio = sum(self.took[n] for n in both) / sum(self.priors[n] for n in both)
        return min(max(ratio, PACE_BOUNDS[0]), PACE_BOUNDS[1])

    def estimate(self, now: float | None = None) -> tuple[float, float | None, bool]:
        """The share of the run done (by expected time), the ETA in s, and whether it is a
        lower bound (a section left has no stored time)."""
        now = time.monotonic() if now is None else now
        pace = self.pace()
        known = [self.priors[n] for n in self.names if self.priors.get(n)]
        typical = sum(known) / len(known) if known else 1.0

        def weight(name: str) -> float:
            return self.priors.get(name) or typical

        def expected(name: str) -> float | None:
            # a section stored as 0.0 s (under 5 ms: the scale model) was measured: it adds
            # nothing to the ETA, and does not make it a lower bound
            prior = self.priors.get(name)
            return None if prior is None else prior * pace

        left = [n for n in self.names if n not in self.took and n != self.current]
        eta = 0.0
        open_ = False
        share_of_current = 0.0
        if self.current is not None:
            elapsed = now - self.started
            whole = expected(self.current)
            if self.step is not None and self.step[0] > 0 and self.step[1] > 0:
                done, total = self.step[:2]
                whole = elapsed / done * total
                share_of_current = done / total
            elif whole:
                share_of_current = min(elapsed / whole, 0.99)
            if whole is None:
                open_ = True
            else:
                eta += max(whole - elapsed, 0.0)
        for name in left:
            exp = expected(name)
            if exp is None:
                open_ = True
            else:
                eta += exp
        all_weight = sum(weight(n) for n in self.names) or 1.0
        done_weight = sum(weight(n) for n in self.took)
        if self.current is not None:
            done_weight += weight(self.current) * share_of_current
        nothing_known = not known and (self.step is None or self.step[0] == 0)
        return done_weight / all_weight, None if nothing_known else eta, open_

    def _detail(self) -> str:
        if self.names and len(self.took) == len(self.names):
            return f"{len(self.names)} sections, then the machine's own checks"
        k = len(self.took) + (1 if self.current else 0)
        text = f"{k}/{len(self.names)} {self.current or ''}".rstrip()
        if self.step is not None:
            done, total, unit, detail = self.step
            text += f" {done}/{total} {unit}" + (f" ({detail})" if detail else "")
        return text

    def _show(self, force: bool = False, draw: bool = True) -> None:
        share, eta, open_ = self.estimate()
        self.bar.update(
            fraction=share,
            detail=self._detail(),
            eta_s=eta,
            eta_open=open_,
            force=force,
            draw=draw,
        )

    def _tick(self) -> None:
        while not self._stop.wait(TICK_S):
            with self._lock:
                self._show(force=True)
