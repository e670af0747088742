"""How much each section measures: the presets behind ``--quick`` and ``--size``.

``full`` is for the committed report on a quiet machine; ``quick`` is a
look in under 90 s (``deepxpalm bench --quick`` also leaves out the sections
marked ``quick=False``); ``smallest`` exists so a test can run every section in
seconds and keep the code from rotting (its numbers mean nothing). Each
section keeps its own sizes per preset; a preset here gathers them.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import asdict
from typing import Any

from harness.bench import sections

# the section names, which the command line offers and the tests check against
SECTIONS = sections.SECTION_NAMES

__all__ = ["PRESETS", "SECTIONS", "Sizes"]


class Sizes(Mapping[str, Any]):
    """One preset: each section's name to its own sizes."""

    def __init__(self, preset: str) -> None:
        self.preset = preset
        self._by_section = {s.name: s.sizes[preset] for s in sections.SECTIONS}

    def __getitem__(self, name: str) -> Any:
        return self._by_section[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._by_section)

    def __len__(self) -> int:
        return len(self._by_section)

    def flat(self) -> dict[str, Any]:
        """Every section's fields in one dict, as the JSON report has always held them.

        Sections that read the same setting (the pace, the nodes' warm-up) must
        agree on it in every preset.
        """
        out: dict[str, Any] = {}
        for name, sizes in self._by_section.items():
            for key, value in asdict(sizes).items():
                if key in out and out[key] != value:
                    raise ValueError(f"{self.preset}: {name} has {key}={value}, another {out[key]}")
                out[key] = value
        return out


PRESETS: dict[str, Sizes] = {p: Sizes(p) for p in ("full", "quick", "smallest")}
