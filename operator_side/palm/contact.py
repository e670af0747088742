"""From a 3x3 stimulus to three contact points, one per linkage (mm).

Row n drives linkage n. A row with no non-zero cell retracts its contact
point off the palm; a cell in column c with v newtons places the point at
X = column_x_mm[c] and presses (v - floor) / (full - floor) of the maximum
depth into the palm.

NumPy only where an array is asked for: the contact mapping is part of the
operator's config, which ``deepxpalm palm lift`` reads without NumPy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from common.config.typed import param
from common.tactile.scale import SATURATION_N

if TYPE_CHECKING:
    import numpy as np


@dataclass(frozen=True)
class ContactMapping:
    retract_point_mm: tuple[float, float] = param(
        (10.0, 40.0), "where a lifted contact rests, off the palm"
    )
    column_x_mm: tuple[float, float, float] = param(
        (-8.0, 10.0, 28.0), "X of stimulus columns 0, 1, 2 across the palm"
    )
    palm_y_mm: float = param(55.0, "Y of the palm's surface")
    max_depth_mm: float = param(6.0, "how far a full-scale force presses into the palm")
    force_floor_n: float = param(1.0, "force that just touches the palm (the sensor's floor)")
    force_full_n: float = param(
        SATURATION_N, "force that presses max_depth_mm (the sensor's saturation)"
    )

    def __post_init__(self) -> None:
        if not self.force_full_n > self.force_floor_n:
            raise ValueError("force_full_n must be larger than force_floor_n")
        if self.max_depth_mm < 0:
            raise ValueError("max_depth_mm must not be negative")


def row_to_point(row: list[float], m: ContactMapping) -> tuple[float, float]:
    """One stimulus row -> contact point. Anything not a positive finite force lifts off."""
    finite = [v if math.isfinite(v) else 0.0 for v in row]
    v = max(finite)
    col = finite.index(v)
    if not v > 0:
        return m.retract_point_mm
    depth = min(max((v - m.force_floor_n) / (m.force_full_n - m.force_floor_n), 0.0), 1.0)
    return (m.column_x_mm[col], m.palm_y_mm + m.max_depth_mm * depth)


def stimulus_to_points(stimulus: Any, m: ContactMapping) -> list[tuple[float, float]]:
    if getattr(stimulus, "shape", None) == (3, 3):
        rows = stimulus.tolist()  # what the codec delivers (an array): one call, exact floats
    else:
        import numpy as np

        rows = np.asarray(stimulus, dtype=np.float64).reshape(3, 3).tolist()
    return [row_to_point(row, m) for row in rows]


def reachable_points(m: ContactMapping, depth_steps: int = 25) -> list[tuple[float, float]]:
    """Every point the mapping can produce: each column over its depth range, and the retract."""
    step = m.max_depth_mm / max(depth_steps - 1, 1)
    depths = [i * step for i in range(depth_steps - 1)] + [m.max_depth_mm]  # as np.linspace
    pts = [(x, m.palm_y_mm + d) for x in m.column_x_mm for d in depths]
    pts.append(m.retract_point_mm)
    return pts


def reachable_set(m: ContactMapping, depth_steps: int = 25) -> np.ndarray:
    """``reachable_points`` as an (N, 2) array."""
    import numpy as np

    return np.array(reachable_points(m, depth_steps), dtype=np.float64)
