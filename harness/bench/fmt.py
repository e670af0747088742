"""Formatting shared by the sections' parts of the report, and pyplot without a display."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

#: two latencies within this fraction are a tie on a shared machine
TIE_FRACTION = 0.10


def num(x: Any, digits: int = 1) -> str:
    """A number with thousands separators; n/a for a missing or non-finite one."""
    if x is None:
        return "n/a"
    if isinstance(x, float) and not math.isfinite(x):
        return "n/a"
    if isinstance(x, (int,)) and not isinstance(x, bool):
        return f"{x:,}"
    return f"{x:,.{digits}f}"


def pct(x: Any, digits: int = 1) -> str:
    return "n/a" if x is None else f"{100 * x:.{digits}f} %"


def sci(x: Any) -> str:
    return "n/a" if x is None else f"{x:.1e}"


def table(header: list[str], rows: list[list[str]], align: str | None = None) -> list[str]:
    """A Markdown table's lines."""
    align = align or ("|" + "---|" * len(header))
    return ["| " + " | ".join(header) + " |", align, *("| " + " | ".join(r) + " |" for r in rows)]


def results_of(results: dict[str, Any], name: str) -> dict[str, Any] | None:
    """A section's results, or None when it was skipped or failed."""
    s = results["sections"].get(name)
    if not s or "error" in s or s.get("skipped"):
        return None
    return s


def pyplot() -> Any:
    """matplotlib's pyplot on the Agg backend (figures are written, never shown)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


#: where the report's figures are, relative to the report
IMG_DIR = "img"


def save_figure(fig: Any, path: Path) -> Path:
    """Every bench figure at the same resolution, its memory given back at once."""
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    pyplot().close(fig)
    return path
