"""The twelve patterns and their masks: another name for that part of ``common.tactile``.

The tactile contract declares them; modules that import them from here keep
working, and new code imports ``common.tactile``.
"""

from common.tactile import (
    ANGLES_DEG,
    MASKS,
    MASKS_F32,
    N_ANGLES,
    N_PATTERNS,
    N_POSITIONS,
    classes_of,
    matches_pattern,
    pattern_name,
    pattern_of,
)

__all__ = [
    "ANGLES_DEG",
    "MASKS",
    "MASKS_F32",
    "N_ANGLES",
    "N_PATTERNS",
    "N_POSITIONS",
    "classes_of",
    "matches_pattern",
    "pattern_name",
    "pattern_of",
]
