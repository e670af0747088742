"""The serial board's counts-to-newtons conversion as one compiled call (numba).

The reference is ``scan_converter.ScanConverter``'s NumPy path: seven array calls
per scan, which on a core gone cold since the last frame cost about 120 us;
this loop costs about half that, most of it the call itself. The arithmetic
is the same float32 operations in the same order (no fast math), so the two
give bit-identical frames (tests/drivers/test_tactile_serial.py).

Importing this module needs numba (the robot extra); the driver falls back
to NumPy without it.
"""

from __future__ import annotations

import numpy as np

from common.tactile.contract import FRAME_SHAPE
from robot_side.jit.cache import njit

_ZERO = np.float32(0.0)


@njit()
def convert_scan(payloads, order, zero, gain, floor, saturation):  # pragma: no cover - compiled
    """Both pads' little-endian uint16 counts -> a new float32 ``FRAME_SHAPE`` frame.

    ``order[k]`` is the wire taxel shown at common-view taxel ``k`` (the
    mirror as a gather); ``zero`` and ``gain`` are already in the common view.
    """
    n = order.shape[0]
    out = np.empty(n, np.float32)
    for k in range(n):
        at = 2 * order[k]
        counts = np.float32(np.int64(payloads[at]) | (np.int64(payloads[at + 1]) << 8))
        newtons = (counts - zero[k]) * gain[k]
        if newtons > saturation:
            newtons = saturation
        if newtons < floor:
            newtons = _ZERO
        out[k] = newtons
    return out.reshape(FRAME_SHAPE)
