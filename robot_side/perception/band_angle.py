"""The band's angle on the pads, in degrees, from the frame's second moments.

The CNN names a class every 45 deg; a pipette at 113 deg is "135" to the
world and may be "90" to the CNN, and a whole-class turn from "45" can land
it there. The assist (robot_side/node/assist.py) turns by this finer angle
when it agrees with the recognised class, and calls a grasp aligned only
when it lies near 90 deg.

Convention (docs/tactile.md): theta from the row direction, counter-clockwise
with "up" towards row 0, in [0, 180). The two pads are summed in the common
view (pad 2 is already mirrored into it). NumPy only; about 0.1 ms, and the assist
calls it once per decision (a re-grasp or "aligned"), never per frame.
"""

from __future__ import annotations

import math

import numpy as np

from common.stimulus import sanitize_frame
from common.tactile import PAD_COLS, PAD_ROWS

#: a taxel below this share of the frame's peak does not weigh in (noise, stuck floors)
FLOOR_SHARE = 0.15
#: the band's length over its width (the moments' eigenvalue ratio) must reach this: a
#: round blob (a tip, a point) has no direction
MIN_ELONGATION = 2.0

_X = np.tile(np.arange(PAD_COLS, dtype=np.float64), (PAD_ROWS, 1))  # right
_Y = -np.repeat(np.arange(PAD_ROWS, dtype=np.float64)[:, None], PAD_COLS, axis=1)  # up


def band_angle_deg(frame: np.ndarray) -> float | None:
    """theta in [0, 180), or None when the contact is too small or round to have one.

    Garbage in (NaN, infinities, negative readings) is held to the sensor's
    range by the node's own ``sanitize_frame``; it never makes an angle up.
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
    if long_axis < MIN_ELONGATION * max(short_axis, 1.0 / 12.0):  # one taxel's own spread
        return None
    theta = 0.5 * math.degrees(math.atan2(2.0 * sxy, sxx - syy))
    return theta % 180.0
