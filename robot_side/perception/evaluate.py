"""Accuracy of a model on labelled frames, per pattern and per grip level, as markdown.

``deepxpalm collect --evaluate DATA.npz [DATA2.npz ...] [--model PATH]``
prints the tables docs/perception.md quotes for collected frames.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from common.tactile.contract import N_GRIP_LEVELS, N_PATTERNS, patterns_of
from robot_side.perception import dataset
from robot_side.perception.inference import load_classifier

POSITIONS = ("centre", "left", "right")


@dataclass
class Accuracy:
    frames: int
    angle: float
    position: float
    pattern: float
    by_pattern: dict[int, tuple[int, float, float]]  # pattern -> (frames, angle, position)
    by_level: dict[int, tuple[int, float, float]]  # grip level -> (frames, angle, position)


def evaluate(paths: list[Path], model: Path | None = None) -> Accuracy:
    sets = [dataset.load(p) for p in paths]
    frames = np.concatenate([d.frames for d in sets])
    angle = np.concatenate([d.angle for d in sets])
    position = np.concatenate([d.position for d in sets])
    level = np.concatenate([d.grip_level for d in sets])
    a, p = load_classifier(model).predict(frames)
    ok_a, ok_p = a == angle, p == position
    pattern = patterns_of(angle, position)

    def rows(keys: np.ndarray, values: range) -> dict[int, tuple[int, float, float]]:
        out = {}
        for k in values:
            m = keys == k
            if m.any():
                out[k] = (int(m.sum()), float(ok_a[m].mean()), float(ok_p[m].mean()))
        return out

    return Accuracy(
        frames=len(frames),
        angle=float(ok_a.mean()),
        position=float(ok_p.mean()),
        pattern=float((ok_a & ok_p).mean()),
        by_pattern=rows(pattern, range(N_PATTERNS)),
        by_level=rows(level, range(1, N_GRIP_LEVELS + 1)),
    )


def markdown(acc: Accuracy, title: str) -> str:
    pct = lambda x: f"{100 * x:.2f} %"  # noqa: E731
    lines = [
        f"**{title}**: {acc.frames} frames; angle {pct(acc.angle)}, position "
        f"{pct(acc.position)}, both {pct(acc.pattern)}",
        "",
        "| pattern | tilt | position | frames | angle | position |",
        "|---|---|---|---|---|---|",
    ]
    for k, (n, a, p) in acc.by_pattern.items():
        lines.append(
            f"| {k} | {45 * (k // 3)} deg | {POSITIONS[k % 3]} | {n} | {pct(a)} | {pct(p)} |"
        )
    lines += ["", "| grip level | frames | angle | position |", "|---|---|---|---|"]
    for k, (n, a, p) in acc.by_level.items():
        lines.append(f"| {k} | {n} | {pct(a)} | {pct(p)} |")
    return "\n".join(lines) + "\n"
