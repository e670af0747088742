"""The twelve tilt/position patterns and their 3x3 masks (docs/tactile.md).

pattern = 3 * angle_class + position_class. Angle classes 0..3 are 0, 45,
90 and 135 degrees; position classes 0..2 are centre, left (up for 0 deg)
and right (down for 0 deg). Both nodes use these: the robot to mask, the
operator to draw and to run the perception study.
"""

from __future__ import annotations

import numpy as np

ANGLES_DEG = (0, 45, 90, 135)
N_ANGLES = 4
N_POSITIONS = 3
N_PATTERNS = N_ANGLES * N_POSITIONS

_CELLS: dict[int, tuple[tuple[int, int], ...]] = {
    0: ((1, 1),),
    1: ((0, 1),),
    2: ((2, 1),),
    3: ((0, 2), (1, 1), (2, 0)),
    4: ((0, 1), (1, 0)),
    5: ((1, 2), (2, 1)),
    6: ((0, 1), (1, 1), (2, 1)),
    7: ((0, 0), (1, 0), (2, 0)),
    8: ((0, 2), (1, 2), (2, 2)),
    9: ((0, 0), (1, 1), (2, 2)),
    10: ((1, 0), (2, 1)),
    11: ((0, 1), (1, 2)),
}

MASKS = np.zeros((N_PATTERNS, 3, 3), dtype=bool)
for _p, _cells in _CELLS.items():
    for _r, _c in _cells:
        MASKS[_p, _r, _c] = True
MASKS.setflags(write=False)
MASKS_F32 = MASKS.astype(np.float32)
MASKS_F32.setflags(write=False)


def pattern_of(angle_class: int, position_class: int) -> int:
    return 3 * int(angle_class) + int(position_class)


def classes_of(pattern: int) -> tuple[int, int]:
    return divmod(int(pattern), 3)


def pattern_name(pattern: int) -> str:
    angle, position = classes_of(pattern)
    side = ("centre", "up", "down") if angle == 0 else ("centre", "left", "right")
    return f"{ANGLES_DEG[angle]} deg {side[position]}"


def matches_pattern(stimulus: np.ndarray, pattern: int) -> bool:
    """True when the stimulus presses exactly the pattern's cells.

    This is what the operator feels: which contact points touch and where.
    It is the project's measure of a stimulus matching "the ideal stimulus
    for the true pattern".
    """
    return bool(np.array_equal(np.asarray(stimulus) > 0, MASKS[pattern]))
