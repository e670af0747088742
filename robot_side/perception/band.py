"""The band on the pads: its angle (deg) and where its axis runs (mm), from second moments.

The CNN names a class every 45 deg and a side every 3 mm; a pipette at 113
deg is "135" to the world and may be "90" to the CNN, and a whole-class turn
from "45" can land it there. A tilted pipette meets the pads up to 10 mm off
their centre, where a fixed sideways step needs a second re-grasp. The assist
(robot_side/node/assist.py) turns and shifts by these finer measures when
they agree with the recognised class, and calls a grasp aligned only when the
angle lies near 90 deg.

Convention (docs/tactile.md): theta from the row direction, counter-clockwise
with "up" towards row 0, in [0, 180); offsets in mm from the pad centre, x
right (along the rows), y up (towards row 0). The two pads are summed in the
common view (pad 2 is already mirrored into it). NumPy only; about 0.1 ms,
and the assist calls it once per decision (a re-grasp or "aligned"), never
per frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from common.tactile.contract import PAD_COLS, PAD_ROWS, TAXEL_PITCH_MM
from common.tactile.stimulus import sanitize_frame

#: a taxel below this share of the frame's peak does not weigh in (noise, stuck floors)
FLOOR_SHARE = 0.15
#: the band's length over its width (the moments' eigenvalue ratio) must reach this: a
#: round blob (a tip, a point) has no direction
MIN_ELONGATION = 2.0

# taxel centres in mm from the pad centre: x right, y up
_X = np.tile((np.arange(PAD_COLS) - (PAD_COLS - 1) / 2) * TAXEL_PITCH_MM, (PAD_ROWS, 1))
_Y = -np.repeat(((np.arange(PAD_ROWS) - (PAD_ROWS - 1) / 2) * TAXEL_PITCH_MM)[:, None], PAD_COLS, 1)
#: one taxel's own spread (mm^2), below which a width is no width
_TAXEL_VARIANCE = TAXEL_PITCH_MM**2 / 12.0


@dataclass(frozen=True)
class Band:
    angle_deg: float  # theta in [0, 180)
    offset_mm: tuple[float, float]  # from the pad centre to the axis, across it (x right, y up)


def measure_band(frame: np.ndarray) -> Band | None:
    """The band's angle and offset, or None when the contact is too small or round.

    Garbage in (NaN, infinities, negative readings) is held to the sensor's
    range by the node's own ``sanitize_frame``; it never makes a band up.
    """
    w = sanitize_frame(frame).astype(np.float64).sum(axis=0)  # the pads in the common view
    peak = float(w.max())
    if not peak > 0.0:
        return None
    w = np.where(w >= FLOOR_SHARE * peak, w, 0.0)
    if np.count_nonzero(w) < 3:
        return None
    total = float(w.sum())
    mx, my = float((w * _X).sum()) / total, float((w * _Y).sum()) / total
    dx, dy = _X - mx, _Y - my
    sxx = float((w * dx * dx).sum()) / total
    syy = float((w * dy * dy).sum()) / total
    sxy = float((w * dx * dy).sum()) / total
    half_trace, diff = 0.5 * (sxx + syy), math.hypot(0.5 * (sxx - syy), sxy)
    long_axis, short_axis = half_trace + diff, half_trace - diff
    if long_axis < MIN_ELONGATION * max(short_axis, _TAXEL_VARIANCE):
        return None
    theta = 0.5 * math.atan2(2.0 * sxy, sxx - syy)
    nx, ny = -math.sin(theta), math.cos(theta)  # across the axis
    across = mx * nx + my * ny  # the centroid's distance from the centre, across the axis
    angle = math.degrees(theta) % 180.0  # a theta a hair below 0 rounds to 180.0 here
    return Band(0.0 if angle >= 180.0 else angle, (across * nx, across * ny))
