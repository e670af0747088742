"""Synthetic tactile frames: the robot side's name for ``common.synthetic_tactile``.

The pad model is NumPy only and lives in ``common`` so the operator's study
can simulate grasps without importing the robot side; the simulated sensors,
the data set and the bench keep importing it from here.
"""

from __future__ import annotations

from common.synthetic_tactile import (
    GeneratorParams,
    Grasp,
    HeldGrasp,
    SyntheticTactileModel,
    mirror_finger2,
    offset_direction,
)
from common.tactile import (
    ANGLES_DEG,
    FRAME_SHAPE,
    N_ANGLES,
    N_GRIP_LEVELS,
    N_PATTERNS,
    N_POSITIONS,
    pattern_of,
)

__all__ = [
    "ANGLES_DEG",
    "FRAME_SHAPE",
    "N_ANGLES",
    "N_GRIP_LEVELS",
    "N_PATTERNS",
    "N_POSITIONS",
    "GeneratorParams",
    "Grasp",
    "HeldGrasp",
    "SyntheticTactileModel",
    "mirror_finger2",
    "offset_direction",
    "pattern_of",
]
