"""The twelve patterns, now part of the tactile contract in ``common.tactile``.

Kept so existing imports keep working; new code imports ``common.tactile``.
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
