"""The tactile contract both nodes share: frames, forces, patterns and grip levels.

Declared once here so the codec, the sensors and their simulators, the
classifier, the renderers and the study cannot drift apart (docs/tactile.md
and docs/architecture.md, "The tactile contract").

- A frame is float32 newtons of shape ``FRAME_SHAPE`` = (2, 10, 10): axis 0
  the pad (0 = finger 1, 1 = finger 2 already mirrored into finger 1's view),
  axis 1 the row (0 at the fingertip end, "up"), axis 2 the column (0 at the
  left).
- A taxel below ``CONTACT_FLOOR_N`` reads 0 and nothing reads above
  ``SATURATION_N``; a frame whose largest taxel reaches the floor holds a
  grasp.
- The stimulus is 3 x 3 newtons, at most one pressed cell per row.
- ``pattern = 3 * angle_class + position_class``: angle classes 0..3 are 0,
  45, 90 and 135 degrees; position classes 0..2 are centre, left (up for
  0 deg) and right (down for 0 deg). ``MASKS`` holds each pattern's cells.
  ``pattern_of`` / ``patterns_of`` encode and ``classes_of`` decodes: no
  other module spells the encoding out (tests/common/test_tactile_contract.py).
- Grip levels run 1 (lightest touch) to ``N_GRIP_LEVELS`` = 31 (strongest
  squeeze): the paper's 31 gripper positions.

NumPy only: the operator node and the study import it without the robot's
dependencies.
"""

from __future__ import annotations

import numpy as np

# the force scale, in a module of its own that needs no NumPy
from common.tactile.scale import CONTACT_FLOOR_N, SATURATION_N  # noqa: F401

N_PADS = 2
PAD_ROWS = 10
PAD_COLS = 10
PAD_SHAPE = (PAD_ROWS, PAD_COLS)
FRAME_SHAPE = (N_PADS, PAD_ROWS, PAD_COLS)
STIMULUS_SHAPE = (3, 3)
#: taxel pitch (mm): 10 taxels over the paper's 5.8 cm^2 pad, about 24.1 mm square
TAXEL_PITCH_MM = 2.41

ANGLES_DEG = (0, 45, 90, 135)
N_ANGLES = 4
N_POSITIONS = 3
N_PATTERNS = N_ANGLES * N_POSITIONS

N_GRIP_LEVELS = 31
#: every valid grip level, lightest first
GRIP_LEVELS = range(1, N_GRIP_LEVELS + 1)

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

MASKS = np.zeros((N_PATTERNS, *STIMULUS_SHAPE), dtype=bool)
for _p, _cells in _CELLS.items():
    for _r, _c in _cells:
        MASKS[_p, _r, _c] = True
MASKS.setflags(write=False)
MASKS_F32 = MASKS.astype(np.float32)
MASKS_F32.setflags(write=False)


def pattern_of(angle_class: int, position_class: int) -> int:
    """The pattern an angle class and a position class name: the one encoding there is."""
    return N_POSITIONS * int(angle_class) + int(position_class)


def patterns_of(angle_classes: np.ndarray, position_classes: np.ndarray) -> np.ndarray:
    """``pattern_of`` element by element, for arrays of classes (a data set, a batch)."""
    return N_POSITIONS * np.asarray(angle_classes) + np.asarray(position_classes)


def classes_of(pattern: int) -> tuple[int, int]:
    """(angle class, position class) of a pattern: ``pattern_of`` undone."""
    return divmod(int(pattern), N_POSITIONS)


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
