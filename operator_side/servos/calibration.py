"""Servo calibration: joint angle (radians) to goal counts, and the limits.

counts = zero_counts + direction * angle * 4096 / (2 pi), then clipped to
[min_counts, max_counts]. The clip is the last word: whatever the stimulus,
the message or the kinematics say, no count outside the limits is produced.
A real device is measured (``deepxpalm calibrate``) and stored in TOML.

The counts are plain numbers (``counts_for``, ``clip_list``: the 60 Hz loop's
size); the array forms import NumPy when first used, so ``deepxpalm palm
lift`` loads a calibration without it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING

from common.config.typed import from_dict, load_toml, param, to_dict
from common.errors import ConfigError

if TYPE_CHECKING:
    import numpy as np

COUNTS_PER_TURN = 4096
COUNTS_PER_RAD = COUNTS_PER_TURN / (2 * math.pi)


@dataclass
class ServoCalibration:
    id: int = param(1, "bus id")
    zero_counts: int = param(2048, "counts at angle 0 (link along +X)")
    direction: int = param(1, "+1 if counts grow counter-clockwise, else -1")
    min_counts: int = param(1024, "lowest count ever commanded")
    max_counts: int = param(3800, "highest count ever commanded")

    def __post_init__(self) -> None:
        if self.direction not in (1, -1):
            raise ConfigError(f"servo {self.id}: direction must be 1 or -1, not {self.direction}")
        if not 0 <= self.min_counts < self.max_counts <= COUNTS_PER_TURN - 1:
            raise ConfigError(
                f"servo {self.id}: limits must satisfy 0 <= min_counts < max_counts <= 4095, "
                f"got [{self.min_counts}, {self.max_counts}]"
            )


def _default_servos() -> list[ServoCalibration]:
    return [ServoCalibration(id=i) for i in range(1, 7)]


@dataclass
class LinkGlideCalibration:
    """Six servos: linkage n uses ids 2n+1 (A side) and 2n+2 (E side)."""

    servos: list[ServoCalibration] = param(_default_servos(), "one entry per servo, ids 1..6")

    def __post_init__(self) -> None:
        ids = [s.id for s in self.servos]
        if sorted(ids) != list(range(1, 7)):
            raise ConfigError(f"calibration must list servo ids 1..6 exactly once, got {ids}")
        by_id = {s.id: s for s in self.servos}
        ordered = [by_id[i] for i in range(1, 7)]
        #: the servo ids, 1..6
        self.id_list = [s.id for s in ordered]
        #: id -> (min, max) counts, for the bus's check of every write
        self.limits_by_id = {s.id: (s.min_counts, s.max_counts) for s in ordered}
        #: (id, zero, counts per radian, min, max) per servo, ids 1..6, as plain numbers
        self._per_servo = [
            (s.id, float(s.zero_counts), s.direction * COUNTS_PER_RAD, s.min_counts, s.max_counts)
            for s in ordered
        ]

    # -- array forms (NumPy imported on first use) --------------------------------

    @cached_property
    def ids(self) -> np.ndarray:
        """The servo ids 1..6 as an int64 array."""
        import numpy as np

        return np.array(self.id_list, dtype=np.int64)

    @cached_property
    def min_counts(self) -> np.ndarray:
        import numpy as np

        return np.array([p[3] for p in self._per_servo], dtype=np.int64)

    @cached_property
    def max_counts(self) -> np.ndarray:
        import numpy as np

        return np.array([p[4] for p in self._per_servo], dtype=np.int64)

    @cached_property
    def _zero_scale(self) -> tuple[np.ndarray, np.ndarray]:
        import numpy as np

        return np.array([p[1] for p in self._per_servo]), np.array([p[2] for p in self._per_servo])

    def angles_to_counts(self, angles: np.ndarray) -> np.ndarray:
        """(3, 2) angles (tau_a, tau_e per linkage) -> (6,) int counts, ids 1..6, clipped.

        Angles are wrapped to (-pi, pi] first; a non-finite angle raises,
        because no safe count can be guessed for it.
        """
        import numpy as np

        flat = np.asarray(angles, dtype=np.float64).reshape(6).tolist()
        return np.array(self.counts_for(flat), dtype=np.int64)

    def counts_for(self, angles: list[float]) -> list[int]:
        """``angles_to_counts`` for six plain floats (tau_a, tau_e per linkage): the hot path."""
        out = []
        for a, (_, zero, scale, lo, hi) in zip(angles, self._per_servo, strict=True):
            if not math.isfinite(a):
                raise ValueError(f"non-finite servo angle(s): {angles}")
            wrapped = math.remainder(a, 2 * math.pi)
            if wrapped == -math.pi:
                wrapped = math.pi
            out.append(min(max(round(zero + scale * wrapped), lo), hi))
        return out

    def clip_list(self, counts: list[int]) -> list[int]:
        """``clip_counts`` for six plain ints (the 60 Hz loop's size)."""
        return [
            min(max(int(c), lo), hi)
            for c, (_, _, _, lo, hi) in zip(counts, self._per_servo, strict=True)
        ]

    def counts_to_angles(self, counts: np.ndarray) -> np.ndarray:
        import numpy as np

        zero, scale = self._zero_scale
        return ((np.asarray(counts, dtype=np.float64).reshape(6) - zero) / scale).reshape(3, 2)

    def clip_counts(self, counts: np.ndarray) -> np.ndarray:
        import numpy as np

        return np.clip(np.asarray(counts, dtype=np.int64), self.min_counts, self.max_counts)

    def within_limits(self, counts: np.ndarray) -> bool:
        import numpy as np

        c = np.asarray(counts)
        return bool(np.all((c >= self.min_counts) & (c <= self.max_counts)))


def load_calibration(path: str | Path) -> LinkGlideCalibration:
    return from_dict(LinkGlideCalibration, load_toml(path), where="calibration")


def save_calibration(calibration: LinkGlideCalibration, path: str | Path) -> None:
    lines = ["# LinkGlide servo calibration (deepxpalm calibrate). counts = zero_counts +"]
    lines.append("# direction * angle * 4096 / (2 pi), clipped to [min_counts, max_counts].")
    for servo in to_dict(calibration)["servos"]:
        lines.append("\n[[servos]]")
        lines.extend(f"{k} = {v}" for k, v in servo.items())
    Path(path).write_text("\n".join(lines) + "\n")
